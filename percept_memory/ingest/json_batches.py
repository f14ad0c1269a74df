"""Request bodies of scenes (JSON) made ready to store in worker processes.

An in-process caller hands over `Scene` objects; a JSON body must first be parsed, validated
into them and encoded into documents, about two thirds of the server's CPU per scene, all of
it holding Python's GIL. So a large body goes to worker processes (`JsonWorkers`): each parses
it and validates and encodes its own contiguous part of the scenes, and hands back only the
encoded documents (BSON bytes) and the ids; this process stores them in one transaction as
IngestService does. Small bodies are done here, where a worker's round trip would cost more.
"""

from __future__ import annotations

import logging
import multiprocessing
from collections.abc import Mapping
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field

from percept_memory.ingest.errors import IngestError
from percept_memory.ingest.json_input import parse
from percept_memory.memory import documents as docs
from percept_memory.memory.settings import collect_less

log = logging.getLogger(__name__)

PARALLEL_BYTES = 1 << 20  # bodies at least this large go to the workers


class NotScenes(ValueError):
    """The body is not JSON, or holds no scene (the message says which)."""


def scenes_of(body: bytes) -> tuple[list, bool]:
    """The items of a body (a scene or a list of scenes) and whether its bytes were
    screened (json_input.parse)."""
    try:
        data, screened = parse(body)
    except ValueError as error:
        raise NotScenes(f"the body is not valid JSON: {error}") from None
    items = data if isinstance(data, list) else [data]
    if not items:
        raise NotScenes("the batch is empty")
    return items, screened


@dataclass
class Part:
    """What a worker made of its part of a body: the problems of its scenes, or their
    documents and ids."""

    problems: list[dict] = field(default_factory=list)
    documents: docs.Documents = field(default_factory=docs.Documents)
    results: list[docs.SceneIds] = field(default_factory=list)


def prepared_part(body: bytes, part: int, parts: int, context: Mapping,
                  threshold: int) -> Part:
    """In a worker: the `part`-th of `parts` contiguous parts of the body's scenes, validated
    (problems named by the scene's index in the whole body) and encoded."""
    from percept_memory.ingest.service import validate  # (the service imports this module)

    items, screened = scenes_of(body)
    start, stop = part * len(items) // parts, (part + 1) * len(items) // parts
    scenes, problems = [], []
    for index in range(start, stop):
        try:
            scenes.append(validate(items[index], context, index, screened))
        except IngestError as error:
            problems += error.problems
    if problems or not scenes:
        return Part(problems)
    prepared = docs.prepared(scenes, {}, threshold)
    return Part(documents=prepared.documents, results=prepared.results)


class JsonWorkers:
    """The worker processes, started on first use (each imports the program: about a second)
    and stopped by `close`."""

    def __init__(self, processes: int):
        self.processes = processes
        self._pool: ProcessPoolExecutor | None = None

    def prepared(self, body: bytes, context: Mapping, threshold: int) -> tuple[
            docs.Documents, list[docs.SceneIds]] | None:
        """The documents and ids of the body's scenes, prepared by the workers, a part each;
        an IngestError naming every problem, or NotScenes. None when a worker died (killed,
        out of memory): the pool starts afresh next time, and the caller does it itself."""
        if self._pool is None:
            self._pool = ProcessPoolExecutor(
                self.processes, mp_context=multiprocessing.get_context("spawn"),
                initializer=collect_less)
        try:
            futures = [self._pool.submit(prepared_part, body, part, self.processes,
                                         dict(context), threshold)
                       for part in range(self.processes)]
            parts: list[Part] = [future.result() for future in futures]
        except BrokenProcessPool:
            log.warning("an ingest worker process died; starting them afresh")
            self.close()
            return None
        problems = [problem for part in parts for problem in part.problems]
        if problems:
            raise IngestError(problems)
        written = docs.Documents()
        for part in parts:
            written.add(part.documents)
        return written, [ids for part in parts for ids in part.results]

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(cancel_futures=True)
            self._pool = None
