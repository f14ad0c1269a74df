"""The one way in: validate -> store -> after-store stages -> ids.

HTTP, the CLI and every importer hand scenes to `IngestService`. A batch is validated whole
before anything is written, so bad input never leaves half a batch behind; the valid batch is
stored in one transaction. Scenes stored before (same robot, same timestamp) are not written
again and keep their ids. After storing, the new scenes go through the after-store stages in
order: identity consolidation, then enqueueing enrichment jobs, as those parts of the memory
register theirs. Ingest never waits on a web lookup.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from itertools import islice
from typing import Any, NamedTuple

from pydantic import ValidationError

from percept_memory.memory.documents import SceneIds
from percept_memory.memory.store import MemoryStore
from percept_memory.memory.types import Scene

AfterStore = Callable[[Sequence[Scene]], None]
"""A stage run on the scenes a batch newly stored (e.g. identity consolidation)."""

DEFAULT_BATCH = 32
UNION_TAGS = {"known", "unknown"}  # arms of polymorphic fields, not part of a field's path


class IngestError(ValueError):
    """Input that is not a valid scene. `problems` holds one entry per problem: which item of
    the batch, the field path (e.g. `clusters.0.annotations.2.confidence`) and what is wrong."""

    def __init__(self, problems: list[dict]):
        self.problems = problems
        lines = [f"{p['item']}: {p['path'] or '(scene)'}: {p['message']}" for p in problems[:10]]
        more = f"\n... and {len(problems) - 10} more" if len(problems) > 10 else ""
        super().__init__(f"{len(problems)} problem(s) in the input:\n" + "\n".join(lines) + more)


class SourceError(ValueError):
    """A file, folder or database that cannot be read as percepts; the message names it and
    says what is wrong (importers' errors derive from this)."""


def problems_of(error: ValidationError, item: Any) -> list[dict]:
    """pydantic's errors as IngestError problems (no input values echoed back)."""
    return [
        {"item": item, "path": ".".join(str(p) for p in e["loc"] if p not in UNION_TAGS),
         "message": e["msg"], "type": e["type"]}
        for e in error.errors(include_url=False, include_input=False)
    ]


def validate(data: Scene | Mapping, context: Mapping | None = None, item: Any = 0) -> Scene:
    """A Scene from a Scene or from interchange data (a dict as parsed from JSON). `context`
    carries what reading it needs, e.g. the scene-log folder that relative paths refer to."""
    if isinstance(data, Scene):
        return data
    if not isinstance(data, Mapping):
        raise IngestError([{"item": item, "path": "", "message":
                            f"a scene is a JSON object, not {type(data).__name__}",
                            "type": "model_type"}])
    try:
        return Scene.model_validate(dict(data), context=dict(context or {}))
    except ValidationError as error:
        raise IngestError(problems_of(error, item)) from None


class IngestService:
    """Brings scenes into a MemoryStore."""

    def __init__(
        self,
        store: MemoryStore,
        *,
        after_store: Sequence[AfterStore] = (),
        batch_size: int = DEFAULT_BATCH,
    ):
        self.store = store
        self.after_store = list(after_store)
        self.batch_size = batch_size

    def ingest(self, data: Scene | Mapping, context: Mapping | None = None) -> SceneIds:
        """Validate and store one scene."""
        return self.ingest_batch([data], context)[0]

    def ingest_batch(
        self,
        items: Sequence[Scene | Mapping],
        context: Mapping | None = None,
        labels: Sequence[str] | None = None,
    ) -> list[SceneIds]:
        """Validate a whole batch, then store it in one transaction; nothing is written when
        any item is invalid (the IngestError names every problem, by label or index)."""
        scenes = self._validated(items, context, labels)
        return self._stored(scenes, self.store.put_scenes(scenes))

    def ingest_stream(
        self, items: Iterable[tuple[str, Scene | Mapping]], context: Mapping | None = None
    ) -> Iterator[Ingested]:
        """Store a long stream of (label, scene) batch by batch (importers, the demo),
        yielding each scene with its ids as its batch lands. Labels name items in errors.

        Pipelined: while a writer thread commits one batch (pymongo waits on the server
        without holding the GIL), this thread validates and encodes the next one."""
        iterator = iter(items)
        landed: list[Ingested] = []
        with ThreadPoolExecutor(max_workers=1, thread_name_prefix="pmem-writer") as writer:
            pending: tuple[list[Scene], Future] | None = None
            try:
                while batch := list(islice(iterator, self.batch_size)):
                    scenes = self._validated([data for _, data in batch], context,
                                             [label for label, _ in batch])
                    prepared = self.store.prepare_scenes(scenes)
                    if pending is not None:
                        previous, pending = pending, None
                        yield from self._landed(*previous)
                    pending = (scenes, writer.submit(self.store.commit_scenes, prepared))
            finally:
                if pending is not None:  # lands (and is consolidated) even if a later batch
                    landed = self._landed(*pending)  # was invalid or the caller stopped
        yield from landed

    def _landed(self, scenes: list[Scene], write: Future) -> list[Ingested]:
        return list(map(Ingested, scenes, self._stored(scenes, write.result())))

    @staticmethod
    def _validated(items, context, labels) -> list[Scene]:
        scenes, problems = [], []
        for index, data in enumerate(items):
            try:
                scenes.append(validate(data, context, item=labels[index] if labels else index))
            except IngestError as error:
                problems.extend(error.problems)
        if problems:
            raise IngestError(problems)
        return scenes

    def _stored(self, scenes: list[Scene], results: list[SceneIds]) -> list[SceneIds]:
        """Run the after-store stages on the scenes that are new, then hand the ids back."""
        created = [scene for scene, ids in zip(scenes, results, strict=True) if ids.created]
        if created:
            for stage in self.after_store:
                stage(created)
        return results


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
