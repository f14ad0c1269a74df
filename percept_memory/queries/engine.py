"""The Python API of queries: QueryEngine (sync) and AsyncQueryEngine, the same methods.

Each method takes its query model, or the same fields as keyword arguments:

    engine = QueryEngine(store)
    engine.clusters(text="Prinles", region="table", where=["classification:confidence>0.8"])
    engine.where_is("the ketchup")

and runs the plan the query modules describe, on the sync or the async driver.
"""

from __future__ import annotations

from typing import Any, TypeVar

from pydantic import BaseModel

from percept_memory.memory.pipeline import rebuilding
from percept_memory.memory.settings import Settings

from . import annotators, questions, stats
from .clusters import find_clusters
from .model import (
    About,
    AnnotatorWindow,
    AtTime,
    Between,
    ClusterFilter,
    ClusterQuery,
    ConfusionCell,
    Cooccurrence,
    History,
    Playback,
    Timings,
)
from .ops import AsyncRunner, Runner
from .playback import playback

M = TypeVar("M", bound=BaseModel)

QUERIES: dict[str, tuple[type[BaseModel], Any]] = {
    "clusters": (ClusterQuery, find_clusters),
    "where_is": (About, questions.where_is),
    "where_was": (History, questions.where_was),
    "last_seen": (About, questions.last_seen),
    "what_is_at": (AtTime, questions.what_is_at),
    "changes": (Between, questions.changes),
    "annotation_stats": (ClusterFilter, stats.annotations),
    "cooccurrence": (Cooccurrence, stats.cooccurrence),
    "timings": (Timings, stats.timings),
    "playback": (Playback, playback),
    "annotator_report": (AnnotatorWindow, annotators.report),
    "annotator_clusters": (ConfusionCell, annotators.cell),
}
"""Every query by name: the model of its question and the plan that answers it. The HTTP
API and the CLI are generated from this table."""

BELIEF_QUERIES = frozenset({"where_is", "where_was", "last_seen", "what_is_at", "changes",
                            "cooccurrence"})
"""The queries answered from the belief: while a map's is being rebuilt (a late scene, a
correction, `pmem reconsolidate`), their answers hold only the scenes consolidated so far."""


def rebuilding_for(db, name: str, query: BaseModel) -> list[str]:
    """The maps being rebuilt whose belief the query reads (none, unless it reads one)."""
    if name not in BELIEF_QUERIES:
        return []
    map_name = getattr(query, "map", None)
    return rebuilding(db, map_name if isinstance(map_name, str) else None)


def as_model(model: type[M], query: M | None, fields: dict) -> M:
    if query is not None and fields:
        raise TypeError("give a query model or keyword fields, not both")
    return query if query is not None else model.model_validate(fields)


def _first_field(model: type[BaseModel]) -> str:
    return next(iter(model.model_fields))


def _bind(name: str, asynchronous: bool):
    model, plan = QUERIES[name]
    first = _first_field(model)

    def prepared(args: tuple, fields: dict) -> BaseModel:
        query = args[0] if args and isinstance(args[0], model) else None
        if args and query is None:  # the first field positionally: where_is("ketchup")
            fields = {first: args[0], **fields}
        return as_model(model, query, fields)

    if asynchronous:
        async def method(self, *args, **fields):
            return await self.runner.run(plan(prepared(args, fields)))
    else:
        def method(self, *args, **fields):
            return self.runner.run(plan(prepared(args, fields)))
    method.__name__ = name
    method.__doc__ = f"{(plan.__doc__ or '').strip()}\n\nQuery: {model.__name__}."
    return method


def _timeout(settings: Settings | None) -> int:
    return (settings or Settings()).query_timeout_ms


class QueryEngine:
    """Queries on a MemoryStore. With `explain=[]` every operation's winning plan is
    recorded in that list (the tests check each query path uses an index)."""

    def __init__(self, store, settings: Settings | None = None, explain: list | None = None):
        self.runner = Runner(store.db, _timeout(settings), explain)


class AsyncQueryEngine:
    """Queries on an AsyncMemoryStore: the same methods as QueryEngine, as coroutines."""

    def __init__(self, store, settings: Settings | None = None):
        self.runner = AsyncRunner(store.db, _timeout(settings))


for _name in QUERIES:  # one method per query, on both engines
    setattr(QueryEngine, _name, _bind(_name, asynchronous=False))
    setattr(AsyncQueryEngine, _name, _bind(_name, asynchronous=True))
