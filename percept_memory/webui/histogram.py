"""The scene log's histogram of scenes over time: the span of the scenes its filters select,
in BARS equal stretches, each a bar as tall as its scenes and a link that sets the log's time
range to it (it works from the keyboard and without a script; static/brush.js adds a drag
across bars, setting the range to their stretch).

Where the span starts and ends is read from the `newest` index (or a filter's own index paired
with time, schema.py), and the bars are counted exactly, a `count` command each, a few at once
(`bar_counts`), within a time budget of its own; a histogram that would take longer is left
out rather than slowing the page.
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta

from pymongo import ASCENDING, DESCENDING
from pymongo.collection import Collection
from pymongo.errors import ExecutionTimeout

BARS = 24
WIDTH, HEIGHT = 960, 64
MIN_HEIGHT = 2  # px: a bar with any scene shows, however tall the tallest
MILLISECOND = 1_000_000  # ns: the finest a browser's time field takes
BUDGET_MS = 80  # counted beside the facet counts (webui/scene_log.py), not after them
COUNTERS = ThreadPoolExecutor(max_workers=3, thread_name_prefix="pmem-histogram")


@dataclass
class Bar:
    start: int  # ns, inclusive
    end: int  # ns, exclusive
    scenes: int
    x: float
    width: float
    height: float

    @property
    def since(self) -> str:
        return _iso(self.start)

    @property
    def until(self) -> str:
        return _iso(self.end - MILLISECOND)  # the log's `until`: through that millisecond


@dataclass
class Histogram:
    bars: list[Bar]
    width: int = WIDTH
    height: int = HEIGHT


def scene_histogram(scenes: Collection, query: Mapping) -> Histogram | None:
    """The histogram of the scenes the query selects; None when there are none, or when
    counting them ran out of time."""
    deadline = time.monotonic() + BUDGET_MS / 1000
    order = [("timestamp", ASCENDING), ("_id", ASCENDING)]
    first = scenes.find_one(query, {"timestamp": 1}, sort=order)
    if first is None:
        return None
    last = scenes.find_one(query, {"timestamp": 1},
                           sort=[(key, DESCENDING) for key, _ in order])
    # whole milliseconds, as the links give them (and as a browser's time field keeps them)
    start = first["timestamp"] // MILLISECOND * MILLISECOND
    step = -(-(last["timestamp"] + MILLISECOND - start) // (BARS * MILLISECOND)) * MILLISECOND
    edges = [start + i * step for i in range(BARS + 1)]
    spans = [{**query, "timestamp": {"$gte": a, "$lt": b}}  # within the query's own range
             for a, b in zip(edges, edges[1:], strict=False)]
    counts = bar_counts(scenes, spans, deadline)
    if counts is None:
        return None
    tallest, width = max(counts), WIDTH / BARS
    return Histogram([Bar(a, b, n, round(i * width, 1), round(width - 1, 1),
                          round(max(HEIGHT * n / tallest, MIN_HEIGHT if n else 0), 1))
                      for i, (a, b, n) in enumerate(zip(edges, edges[1:], counts,
                                                        strict=False))])


def bar_counts(scenes: Collection, spans: list[dict], deadline: float) -> list[int] | None:
    """Each span's count, by `count` commands, COUNTERS at a time (an index decides each
    from its keys, COUNT_SCAN, and mongod counts two on two cores: over 200,000 scenes
    unfiltered 42 ms, where one aggregation of all the bars took 80; each has a time range,
    so a sharded cluster counts it exactly too); None when the time (time.monotonic) ran
    out first."""
    def count(span: dict) -> int:
        left_ms = int((deadline - time.monotonic()) * 1000)
        if left_ms <= 0:
            raise ExecutionTimeout("no time left to count", code=50)
        return scenes.database.command("count", scenes.name, query=span,
                                       maxTimeMS=left_ms)["n"]

    try:
        return list(COUNTERS.map(count, spans))
    except ExecutionTimeout:
        return None


def _iso(nanoseconds: int) -> str:
    """A time as the log's `since` and `until` take it, to the millisecond (a browser's
    datetime-local field takes no finer), UTC."""
    moment = EPOCH + timedelta(milliseconds=nanoseconds // MILLISECOND)  # (no float rounding)
    return moment.strftime("%Y-%m-%dT%H:%M:%S.%f")[:-3]


EPOCH = datetime(1970, 1, 1, tzinfo=UTC)
