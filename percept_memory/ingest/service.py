"""The one way in: validate -> store (with the outbox) -> ids.

HTTP, the CLI and every importer hand scenes to `IngestService`. A batch is validated whole
before anything is committed, so bad input never leaves half a batch behind; the valid batch
is stored in one transaction (its first scenes sent while the next are being validated; the
transaction is abandoned if any is invalid), each new scene with its outbox entry: the
after-store stages (identity consolidation, enqueueing lookups) then run from the outbox in the
memory pipeline (memory/pipeline.py), exactly once, in time order per map. Ingest answers once
the scenes are durably stored; a caller that needs the belief updated first waits for it
(`wait`). Scenes stored before (same robot, same timestamp) are not written again and keep
their ids.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterable, Iterator, Mapping, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from itertools import islice
from typing import Any, NamedTuple

from pydantic import ValidationError

from percept_memory.ingest.errors import IngestError
from percept_memory.ingest.jobs import LookupEnqueuer
from percept_memory.ingest.json_batches import (
    PARALLEL_BYTES,
    BadLine,
    JsonWorkers,
    Part,
    WorkersDied,
    lines_of,
    read_lines,
    scenes_of,
)
from percept_memory.ingest.json_input import input_problems
from percept_memory.memory.catalogue.stage import CatalogueStage
from percept_memory.memory.consolidation import Consolidation, as_evidence
from percept_memory.memory.documents import Documents, SceneIds
from percept_memory.memory.pipeline import Pipeline
from percept_memory.memory.settings import Settings
from percept_memory.memory.store import MemoryStore
from percept_memory.memory.types import Scene

DEFAULT_BATCH = 32
CHUNK = 8  # scenes of a batch sent to the server while the next ones are validated
UNION_TAGS = {"known", "unknown"}  # arms of polymorphic fields, not part of a field's path


def problems_of(error: ValidationError, item: Any) -> list[dict]:
    """pydantic's errors as IngestError problems (no input values echoed back)."""
    return [
        {"item": item, "path": ".".join(str(p) for p in e["loc"] if p not in UNION_TAGS),
         "message": e["msg"].removeprefix("Value error, "), "type": e["type"]}
        for e in error.errors(include_url=False, include_input=False)
    ]


def validate(data: Scene | Mapping, context: Mapping | None = None, item: Any = 0,
             screened: bool = False) -> Scene:
    """A Scene from a Scene or from interchange data (a dict as parsed from JSON). `context`
    carries what reading it needs, e.g. the scene-log folder that relative paths refer to.
    `screened`: the data was parsed from JSON text that passed json_input.screened, so walking
    it for input_problems would find nothing. A BadLine (NDJSON) is refused as it says."""
    if isinstance(data, Scene):
        return data
    if isinstance(data, BadLine):
        raise IngestError([{"item": item, "path": "", "message": data.message,
                            "type": "json_invalid"}])
    if not isinstance(data, Mapping):
        raise IngestError([{"item": item, "path": "", "message":
                            f"a scene is a JSON object, not {type(data).__name__}",
                            "type": "model_type"}])
    if not screened and (problems := input_problems(data)):
        raise IngestError([{"item": item, **problem} for problem in problems])
    try:
        return Scene.model_validate(dict(data), context=dict(context or {}))
    except ValidationError as error:
        raise IngestError(problems_of(error, item)) from None


class IngestService:
    """Brings scenes into a MemoryStore."""

    def __init__(self, store: MemoryStore, *, pipeline: Pipeline | None = None,
                 batch_size: int = DEFAULT_BATCH, settings: Settings | None = None):
        settings = settings or Settings()
        self.store = store
        self.pipeline = pipeline or memory_pipeline(store, settings)
        self.batch_size = batch_size
        self.limits = {"max_image_pixels": settings.max_image_pixels,
                       "max_crop_pixels": settings.max_crop_pixels}  # for validation
        self.json_workers = (JsonWorkers(settings.ingest_processes, settings.types)
                             if settings.ingest_processes > 1 else None)

    def close(self) -> None:
        """Stop the worker processes, if any were started."""
        if self.json_workers is not None:
            self.json_workers.close()

    def ingest_json(self, body: bytes, ndjson: bool = False) -> list[SceneIds]:
        """Store the scenes of a JSON body (a scene or a list of them, as GET
        /api/schema/scene describes), or with `ndjson` of an NDJSON body (one scene a line,
        blank lines skipped), as ingest_batch does; NotScenes when it holds none. A large
        body is parsed, validated and encoded by the worker processes, a part each
        (json_batches.py), each part stored as it comes; what they could not make (a worker
        died) or what cannot be stored as they made it (a scene stored before, a write too
        large) goes the usual way."""
        with self.pipeline.ingesting():
            results = None
            if self.json_workers is not None and len(body) >= PARALLEL_BYTES:
                results = self._made_by_workers(body, ndjson)
            if results is None:
                items, screened = _scenes(body, ndjson)
                results = self.ingest_batch(items, screened=screened)
        return results

    def _made_by_workers(self, body: bytes, ndjson: bool) -> list[SceneIds] | None:
        """The ids of the body's scenes, stored as the workers make them; None when that could
        not be done, and nothing was stored."""
        results: list[SceneIds] = []
        parts = self.json_workers.prepared(body, ndjson, self.limits,
                                           self.store.gridfs_threshold)
        try:
            if not self.store.put_document_chunks(_documents(parts, results)):
                return None
        except WorkersDied:
            return None
        finally:
            parts.close()
        return self._stored(results)

    def ingest(self, data: Scene | Mapping, context: Mapping | None = None,
               wait: float | None = None) -> SceneIds:
        """Validate and store one scene (see ingest_batch)."""
        return self.ingest_batch([data], context, wait=wait)[0]

    def ingest_batch(
        self,
        items: Sequence[Scene | Mapping],
        context: Mapping | None = None,
        labels: Sequence[str] | None = None,
        wait: float | None = None,
        screened: bool = False,
    ) -> list[SceneIds]:
        """Validate a whole batch, then store it in one transaction; nothing is written when
        any item is invalid (the IngestError names every problem, by label or index). With
        `wait` (seconds), also wait until the scenes went through the pipeline (their
        belief is current), at most that long: `settled` tells whether they did. `screened`:
        as for `validate`."""
        with self.pipeline.ingesting():
            validated: list[Scene] = []
            chunks = self._validated_chunks(items, context, labels, screened)
            results = self.store.put_scene_chunks(_kept(chunks, validated))
            self.store.handed_over.put(
                as_evidence(scene) for item, scene, ids in zip(items, validated, results,
                                                               strict=True)
                if ids.created and not isinstance(item, Scene))  # (made here, not a caller's)
            self._stored(results, {scene.map for scene in validated})
        if wait is not None:
            self.settled(results, wait)
        return results

    def settled(self, results: Sequence[SceneIds], timeout: float) -> bool:
        """Wait until these scenes went through the pipeline and their maps' belief is current
        (True), at most `timeout` seconds (False): those stored before too (a robot's retry may
        come before the first was consolidated)."""
        return self.pipeline.wait([r.scene_id for r in results], timeout)

    def ingest_stream(
        self, items: Iterable[tuple[str, Scene | Mapping]], context: Mapping | None = None
    ) -> Iterator[Ingested]:
        """Store a long stream of (label, scene) batch by batch (importers, the demo),
        yielding each scene with its ids as its batch lands. Labels name items in errors.
        An invalid batch is not stored; every scene before it is, and is yielded before the
        IngestError is raised, so the caller can say exactly what was stored.

        Pipelined: while a writer thread commits one batch (pymongo waits on the server
        without holding the GIL), this thread validates and encodes the next one."""
        landed: list[Ingested] = []
        with ThreadPoolExecutor(max_workers=1, thread_name_prefix="pmem-writer") as writer:
            pending: tuple[list[Scene], Future] | None = None
            try:
                for scenes in self._batches(items, context):
                    prepared = self.store.prepare_scenes(scenes)
                    if pending is not None:
                        previous, pending = pending, None
                        yield from self._landed(*previous)
                    pending = (scenes, writer.submit(self.store.commit_scenes, prepared))
            except IngestError:
                if pending is not None:
                    previous, pending = pending, None
                    yield from self._landed(*previous)
                raise
            finally:
                if pending is not None:  # lands even if the caller stopped
                    landed = self._landed(*pending)
        yield from landed

    def _batches(self, items: Iterable[tuple[str, Scene | Mapping]],
                 context: Mapping | None) -> Iterator[list[Scene]]:
        iterator = iter(items)
        while batch := list(islice(iterator, self.batch_size)):
            yield self._validated([data for _, data in batch], context,
                                  [label for label, _ in batch])

    def _landed(self, scenes: list[Scene], write: Future) -> list[Ingested]:
        return list(map(Ingested, scenes, self._stored(write.result())))

    def _validated(self, items, context, labels) -> list[Scene]:
        return [scene for chunk in self._validated_chunks(items, context, labels)
                for scene in chunk]

    def _validated_chunks(self, items, context, labels, screened=False) -> Iterator[list[Scene]]:
        """The items validated, CHUNK at a time while all are valid (to be stored while the
        next are validated); in the end an IngestError naming every problem, if any."""
        context = {**self.limits, **(context or {})}
        chunk, problems = [], []
        for index, data in enumerate(items):
            try:
                chunk.append(validate(data, context, labels[index] if labels else index,
                                      screened))
            except IngestError as error:
                problems.extend(error.problems)
            if len(chunk) == CHUNK and not problems:
                yield chunk
                chunk = []
        if problems:
            raise IngestError(problems)
        if chunk:
            yield chunk

    def _stored(self, results: list[SceneIds], maps: Iterable[str] = ()) -> list[SceneIds]:
        """Tell the pipeline there is work (when new scenes were stored: of these maps, when
        known); hand the ids back."""
        if any(r.created for r in results):
            self.pipeline.wake(maps)
        return results


def _kept(chunks: Iterable[list[Scene]], kept: list[Scene]) -> Iterator[list[Scene]]:
    """The chunks, their scenes kept in `kept` as they go by."""
    for chunk in chunks:
        kept += chunk
        yield chunk


def _scenes(body: bytes, ndjson: bool) -> tuple[list, bool]:
    """A body's items and whether they were all screened (json_input.parse)."""
    if not ndjson:
        return scenes_of(body)
    read = read_lines(lines_of(body))
    return [item for item, _ in read], all(screened for _, screened in read)


def _documents(parts: Iterable[Part], results: list[SceneIds]) -> Iterator[Documents]:
    """The documents of each part, their ids added to `results`, while no part had a problem;
    in the end an IngestError naming every problem of every part, if any."""
    problems: list[dict] = []
    for part in parts:
        problems += part.problems
        if not problems:
            results += part.results
            yield part.documents
    if problems:
        raise IngestError(problems)


def memory_pipeline(store: MemoryStore, settings: Settings | None = None) -> Pipeline:
    """The memory pipeline with its stages: identity consolidation, with the long-term
    catalogue learnt scene by scene as identity decides (and recalling for it what it took for
    new), then lookup jobs."""
    lease_s = (settings or Settings()).map_lease_s
    identity = Consolidation(store)
    identity.catalogue = CatalogueStage(store, identity=identity)  # learnt as identity decides
    return Pipeline(store, [identity, LookupEnqueuer(store)], lease_s=lease_s)


def in_map(scenes: Iterable[Scene], name: str) -> Iterator[Scene]:
    """The scenes, each placed in the named map (an importer's site: a dump, a folder)."""
    for scene in scenes:
        scene.map = name
        yield scene


class Ingested(NamedTuple):
    scene: Scene
    ids: SceneIds


@dataclass
class ImportSummary:
    """What an import brought in: scenes new and already stored, clusters, kinds of evidence."""

    scenes_new: int = 0
    scenes_existing: int = 0
    clusters: int = 0
    types: Counter = field(default_factory=Counter)

    def add(self, ingested: Ingested) -> None:
        if not ingested.ids.created:
            self.scenes_existing += 1
            return
        self.scenes_new += 1
        self.clusters += len(ingested.scene.clusters)
        for cluster in ingested.scene.clusters:
            self.types.update(item.type_name for item in (*cluster.hypotheses,
                                                            *cluster.annotations))
