"""Database operations as data, and the runners that carry them out.

A query is a plan: a generator that yields operations (Find, Aggregate, Count) and receives
their results, so the logic of every query is written once and runs on the synchronous
(pymongo) or the asynchronous (AsyncMongoClient) driver alike. Every operation carries the
server-side time limit (maxTimeMS); a runner can also record each operation's winning plan
(explain), which is how the tests check that every query path uses an index.
"""

from __future__ import annotations

import re
from collections.abc import Generator
from dataclasses import dataclass
from typing import Any, TypeVar

from bson.min_key import MinKey
from pymongo.errors import ExecutionTimeout

from percept_memory.memory.errors import StoreError

T = TypeVar("T")


class QueryError(StoreError):
    """A query that cannot be answered as asked (its message says why)."""


class QueryTimeout(QueryError):
    def __init__(self, limit_ms: int):
        super().__init__(f"the query took longer than the limit of {limit_ms} ms "
                         "(PMEM_QUERY_TIMEOUT_MS): narrow it down (time, region, text, ...), "
                         "or give the field of a `where` predicate an index of its own "
                         "(pmem index add TYPE:FIELD)")


@dataclass(frozen=True)
class Find:
    collection: str
    filter: dict
    projection: dict | None = None
    sort: tuple[tuple[str, int], ...] = ()
    limit: int = 0

    def command(self) -> dict:
        command: dict[str, Any] = {"find": self.collection, "filter": self.filter}
        if self.projection is not None:
            command["projection"] = self.projection
        if self.sort:
            command["sort"] = dict(self.sort)
        if self.limit:
            command["limit"] = self.limit
        return command


@dataclass(frozen=True)
class Aggregate:
    collection: str
    pipeline: list[dict]

    def command(self) -> dict:
        return {"aggregate": self.collection, "pipeline": self.pipeline, "cursor": {}}


@dataclass(frozen=True)
class Count:
    """The `count` command, not countDocuments' aggregation ($match, $group): the server
    answers a count an index alone decides from the index keys (COUNT_SCAN) and a quarter
    faster (bench/vs_fiftyone.py). A count of everything counts the _id index's keys:
    without a filter the command answers from the collection's metadata, which an unclean
    shutdown or a sharded cluster's orphaned documents can leave wrong."""

    collection: str
    filter: dict

    def command(self) -> dict:
        return {"count": self.collection, "query": self.filter or {"_id": {"$gte": MinKey()}}}


Op = Find | Aggregate | Count
Plan = Generator[Op, Any, T]


def _cursor_args(op: Find, limit_ms: int) -> dict:
    return {"filter": op.filter, "projection": op.projection, "sort": list(op.sort) or None,
            "limit": op.limit, "max_time_ms": limit_ms}


class Runner:
    """Carries out plans on a pymongo database."""

    def __init__(self, db, limit_ms: int, explain: list | None = None):
        self.db, self.limit_ms, self.explained = db, limit_ms, explain

    def run(self, plan: Plan[T]) -> T:
        try:
            result = None
            while True:
                op = plan.send(result)
                if self.explained is not None:
                    self.explained.append(summary(op, self.db.command("explain", op.command())))
                result = self._execute(op)
        except StopIteration as done:
            return done.value
        except ExecutionTimeout:
            raise QueryTimeout(self.limit_ms) from None

    def _execute(self, op: Op) -> Any:
        collection = self.db[op.collection]
        if isinstance(op, Find):
            return list(collection.find(**_cursor_args(op, self.limit_ms)))
        if isinstance(op, Aggregate):
            return list(collection.aggregate(op.pipeline, maxTimeMS=self.limit_ms))
        return self.db.command({**op.command(), "maxTimeMS": self.limit_ms})["n"]


class AsyncRunner:
    """Carries out the same plans on a pymongo AsyncMongoClient database."""

    def __init__(self, db, limit_ms: int):
        self.db, self.limit_ms = db, limit_ms

    async def run(self, plan: Plan[T]) -> T:
        try:
            result = None
            while True:
                result = await self._execute(plan.send(result))
        except StopIteration as done:
            return done.value
        except ExecutionTimeout:
            raise QueryTimeout(self.limit_ms) from None

    async def _execute(self, op: Op) -> Any:
        collection = self.db[op.collection]
        if isinstance(op, Find):
            return await collection.find(**_cursor_args(op, self.limit_ms)).to_list()
        if isinstance(op, Aggregate):
            cursor = await collection.aggregate(op.pipeline, maxTimeMS=self.limit_ms)
            return await cursor.to_list()
        return (await self.db.command({**op.command(), "maxTimeMS": self.limit_ms}))["n"]


_STAGE = re.compile(r"'stage': '(\w+)'")
_INDEX = re.compile(r"'indexName': '([^']+)'")


def summary(op: Op, explained: dict) -> dict:
    """What an explain says about one operation: its collection, the stages of the plans the
    server chose, and the indexes they use."""
    chosen = _winning_plans(explained)
    text = repr(chosen)
    return {"collection": op.collection, "op": type(op).__name__,
            "stages": sorted(set(_STAGE.findall(text))),
            "indexes": sorted(set(_INDEX.findall(text)))}


def _winning_plans(node: Any) -> list:
    if isinstance(node, dict):
        if "winningPlan" in node:
            return [node["winningPlan"]]
        return [plan for value in node.values() for plan in _winning_plans(value)]
    if isinstance(node, list):
        return [plan for value in node for plan in _winning_plans(value)]
    return []
