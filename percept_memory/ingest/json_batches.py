"""Request bodies of scenes (JSON or NDJSON) made ready to store in worker processes.

An in-process caller hands over `Scene` objects; a body must first be parsed, validated into
them and encoded into documents, about two thirds of the server's CPU per scene, all of it
holding Python's GIL. So a large body goes to worker processes (`JsonWorkers`), a part each,
which hand back only the encoded documents (BSON bytes) and the ids; this process stores them
in one transaction as IngestService does. Small bodies are done here, where a worker's round
trip would cost more.

Parts of a JSON array cannot be cut out without parsing it, so each worker parses the whole
body and keeps its share of the scenes. An NDJSON body (one scene a line) is cut at its line
breaks here: each part travels and is parsed alone, so it is cut finer than one part a worker
and each part is stored while the workers make the next ones.
"""

from __future__ import annotations

import logging
import multiprocessing
from collections.abc import Iterator, Mapping
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from itertools import pairwise
from typing import Any, NamedTuple

from percept_memory.ingest.errors import IngestError
from percept_memory.ingest.json_input import parse
from percept_memory.memory import documents as docs
from percept_memory.memory.settings import collect_less
from percept_memory.memory.types.modules import import_type_modules

log = logging.getLogger(__name__)

PARALLEL_BYTES = 1 << 20  # bodies at least this large go to the workers
LINE_PARTS_PER_WORKER = 4  # NDJSON: the last part's storing is all that does not overlap


class NotScenes(ValueError):
    """The body is not JSON, or holds no scene (the message says which)."""


class WorkersDied(RuntimeError):
    """A worker process died (killed, out of memory): the caller does the work itself."""


class BadLine(NamedTuple):
    """An NDJSON line that is not JSON; validating it raises the problem, named by the scene's
    place like any other (ingest/service.py validate)."""

    message: str


def scenes_of(body: bytes) -> tuple[list, bool]:
    """The items of a JSON body (a scene or a list of scenes) and whether its bytes were
    screened (json_input.parse)."""
    try:
        data, screened = parse(body)
    except ValueError as error:
        raise NotScenes(f"the body is not valid JSON: {error}") from None
    items = data if isinstance(data, list) else [data]
    if not items:
        raise NotScenes("the batch is empty")
    return items, screened


def lines_of(body: bytes) -> list[tuple[int, bytes]]:
    """The lines of an NDJSON body that are not blank, with their numbers (from 1)."""
    lines = [(number, line) for number, line in enumerate(body.split(b"\n"), 1)
             if line and not line.isspace()]
    if not lines:
        raise NotScenes("the batch is empty")
    return lines


def read_lines(lines: list[tuple[int, bytes]]) -> list[tuple[Any, bool]]:
    """Each line's JSON value and whether it was screened; a BadLine for one that is not JSON."""
    read = []
    for number, line in lines:
        try:
            read.append(parse(line))
        except ValueError as error:
            read.append((BadLine(f"line {number} is not valid JSON: {error}"), True))
    return read


@dataclass
class ArrayPart:
    """The `part`-th of `parts` contiguous shares of the scenes of a JSON body."""

    body: bytes
    part: int
    parts: int

    def scenes(self) -> tuple[int, list[tuple[Any, bool]]]:
        """The index of the share's first scene in the body, and its scenes as read_lines."""
        items, screened = scenes_of(self.body)
        start = self.part * len(items) // self.parts
        stop = (self.part + 1) * len(items) // self.parts
        return start, [(item, screened) for item in items[start:stop]]


@dataclass
class LinesPart:
    """Lines of an NDJSON body, the first being its scene number `first` (from 0)."""

    first: int
    lines: list[tuple[int, bytes]]

    def scenes(self) -> tuple[int, list[tuple[Any, bool]]]:
        return self.first, read_lines(self.lines)


@dataclass
class Part:
    """What a worker made of its part of a body: the problems of its scenes, or their
    documents and ids."""

    problems: list[dict] = field(default_factory=list)
    documents: docs.Documents = field(default_factory=docs.Documents)
    results: list[docs.SceneIds] = field(default_factory=list)


def prepared_part(part: ArrayPart | LinesPart, context: Mapping, threshold: int) -> Part:
    """In a worker: the part's scenes validated (problems named by the scene's index in the
    whole body) and encoded."""
    from percept_memory.ingest.service import validate  # (the service imports this module)

    first, items = part.scenes()
    scenes, problems = [], []
    for index, (item, screened) in enumerate(items, first):
        try:
            scenes.append(validate(item, context, index, screened))
        except IngestError as error:
            problems += error.problems
    if problems or not scenes:
        return Part(problems)
    prepared = docs.prepared(scenes, {}, threshold)
    return Part(documents=prepared.documents, results=prepared.results)


def body_parts(body: bytes, ndjson: bool, workers: int) -> list[ArrayPart | LinesPart]:
    """A body cut into the parts the workers make (NotScenes for an NDJSON body of no line)."""
    if not ndjson:
        return [ArrayPart(body, part, workers) for part in range(workers)]
    lines = lines_of(body)
    parts = min(len(lines), workers * LINE_PARTS_PER_WORKER)
    bounds = [part * len(lines) // parts for part in range(parts + 1)]
    return [LinesPart(start, lines[start:stop]) for start, stop in pairwise(bounds)]


def worker_started(type_modules: str) -> None:
    """A worker process as the server's: the same annotation types, collecting as seldom."""
    collect_less()
    import_type_modules(type_modules)


class JsonWorkers:
    """The worker processes, started on first use (each imports the program: about a second)
    and stopped by `close`. `type_modules`: PMEM_TYPES, imported by each."""

    def __init__(self, processes: int, type_modules: str = ""):
        self.processes = processes
        self.type_modules = type_modules
        self._pool: ProcessPoolExecutor | None = None

    def prepared(self, body: bytes, ndjson: bool, context: Mapping,
                 threshold: int) -> Iterator[Part]:
        """The parts of the body, made by the workers, in order, each as soon as it and those
        before it are made. NotScenes when the body holds none; WorkersDied when a worker
        died: the pool starts afresh next time."""
        parts = body_parts(body, ndjson, self.processes)
        if self._pool is None:
            self._pool = ProcessPoolExecutor(
                self.processes, mp_context=multiprocessing.get_context("spawn"),
                initializer=worker_started, initargs=(self.type_modules,))
        futures = []
        try:
            futures += [self._pool.submit(prepared_part, part, dict(context), threshold)
                        for part in parts]
            for future in futures:
                yield future.result()
        except BrokenProcessPool:
            log.warning("an ingest worker process died; starting them afresh")
            self.close()
            raise WorkersDied from None
        finally:
            for future in futures:  # those not started, when the caller stopped early
                future.cancel()

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(cancel_futures=True)
            self._pool = None
