"""The catalogue stage when a transaction does not commit: what it learnt in memory for the
aborted batch is forgotten, so the catalogue still equals the one rebuilt from the scenes."""

from __future__ import annotations

from collections import Counter

from percept_memory.demo import kitchen_week
from percept_memory.ingest.service import IngestService, memory_pipeline
from percept_memory.memory.catalogue.stage import MODELS_PER_OBJECT, CatalogueStage
from percept_memory.memory.consolidation import Consolidation
from percept_memory.memory.pipeline import Pipeline, request_rebuild
from percept_memory.memory.schema import CATALOGUE

from .conftest import ingest_consolidated
from .test_catalogue_store import stored_catalogue
from .test_pipeline import BELIEF, Failing


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


def test_an_object_seen_for_weeks_keeps_one_entry_s_worth_of_models(store):
    """Each track made a model every OBSERVATIONS_PER_MODEL sightings and kept them all:
    after a month of the kitchen 215 models in 86 entries for 20 items (4.3 an item; 18.8
    after four months), as an entry holds MODELS_PER_ENTRY. The redundant ones are forgotten,
    the same live and rebuilt."""
    for name in (*BELIEF, "scenes", "clusters", "jobs"):
        store.db[name].delete_many({})
    week = kitchen_week.generate(days=24, seed=0)
    ingest_consolidated(store, week.scenes)
    truth = {cluster.id: week.truth.object_at(i, j)
             for i, scene in enumerate(week.scenes) for j, cluster in enumerate(scene.clusters)}
    models = list(store.db[CATALOGUE].find({}, {"object_id": 1, "entry": 1}))
    per_object = Counter(m["object_id"] for m in models)
    assert max(per_object.values()) == MODELS_PER_OBJECT  # (some were forgotten)
    entries: dict = {}
    for m in models:
        entries.setdefault(m["entry"], set()).add(truth[m["_id"]].partition("#")[0])
    assert all(len(kinds) == 1 for kinds in entries.values())
    assert len(entries) <= 1.5 * len(set(truth.values()))  # (28 for 20: twins apart)
    live = stored_catalogue(store)
    request_rebuild(store)
    memory_pipeline(store).drain(timeout=600)
    assert stored_catalogue(store) == live
