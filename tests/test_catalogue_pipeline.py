"""The catalogue stage when a transaction does not commit: what it learnt in memory for the
aborted batch is forgotten, so the catalogue still equals the one rebuilt from the scenes."""

from __future__ import annotations

from percept_memory.demo import kitchen_week
from percept_memory.ingest.service import IngestService, memory_pipeline
from percept_memory.memory.catalogue.stage import CatalogueStage
from percept_memory.memory.consolidation import Consolidation
from percept_memory.memory.pipeline import Pipeline, request_rebuild

from .test_catalogue_store import stored_catalogue
from .test_pipeline import Failing


class FailingOnce(Failing):
    """A stage after identity's (and its catalogue's) that fails the first time it sees one
    of these scenes."""

    name = "failing_once"

    def apply(self, scene_ids, map_name, session):
        try:
            super().apply(scene_ids, map_name, session)
        finally:
            self.bad -= set(scene_ids)


def test_aborted_batches_leave_no_trace_in_the_catalogue(store):
    scenes = kitchen_week.generate(days=2).scenes
    ids = IngestService(store).ingest_batch(scenes)
    identity = Consolidation(store)
    failing = FailingOnce({i.scene_id for i in ids[5::4]})
    identity.catalogue = CatalogueStage(store, identity=identity)
    pipeline = Pipeline(store, [identity, failing], backoff_s=0.01, batch=4)
    pipeline.drain(timeout=120)
    assert not pipeline.pending()
    live = stored_catalogue(store)
    assert live[0]
    request_rebuild(store)
    memory_pipeline(store).drain(timeout=120)
    assert stored_catalogue(store) == live
