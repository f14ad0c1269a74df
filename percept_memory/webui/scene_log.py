"""The scene log: scenes newest first, SCENES_PER_PAGE at a time, filtered by robot, time range,
region, annotator (a log line's or an annotation's source) and annotation type. Each filter
reads one field of the scene document that an index pairs with (timestamp, _id)
(memory/schema.py): `robot`, `timestamp`, and the inline summary's `regions`, `annotators` and
`types` (memory/documents.py: scene_summary). The cursor `before` is the (timestamp, id) of the
last scene shown, so paging stays exact, filtered or not, while scenes arrive. Each value a
filter offers shows how many scenes it would select with the other filters (facets.py), and a
histogram of the selected scenes over time sets the time range by its bars (histogram.py):
a bar's link, or a drag across bars (static/brush.js).
"""

from __future__ import annotations

import asyncio
from urllib.parse import urlencode

from bson import ObjectId
from fastapi import APIRouter, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import HTMLResponse
from pymongo import DESCENDING

from percept_memory.memory.store import MemoryStore
from percept_memory.queries.model import canonical_type

from .facets import facet_counts, shown
from .histogram import Bar, scene_histogram
from .html import (
    LIST_FIELDS,
    SCRIPT_CSP,
    PageError,
    nanoseconds,
    nanoseconds_through,
    offered,
    page,
    time_input_type,
)

SCENES_PER_PAGE = 20
CHOICES = {"robot": "robot", "region": "summary.regions", "annotator": "summary.annotators",
           "type": "summary.types"}
"""The filters that pick one stored value, and the scene field each one matches."""
FILTERS = (*CHOICES, "since", "until")


def routes(store: MemoryStore) -> APIRouter:
    router = APIRouter(include_in_schema=False, default_response_class=HTMLResponse)

    @router.get("/")
    @router.get("/scenes")
    async def scene_log(request: Request, robot: str = "", region: str = "",
                        annotator: str = "", type: str = "", since: str = "", until: str = "",
                        before: str = "") -> HTMLResponse:
        filters = {"robot": robot, "region": region, "annotator": annotator, "type": type,
                   "since": since, "until": until}

        def choose() -> tuple[dict[str, list[str]], dict]:
            choices = {name: offered(store.scenes, key) for name, key in CHOICES.items()}
            return choices, scene_filter(filters, choices["type"])

        after = _cursor(before) if before else None  # (a bad cursor: a 422 before any work)

        def listed(query: dict) -> list[dict]:
            if after:
                stamp, scene_id = after
                query = {"$and": [query, {"$or": [
                    {"timestamp": {"$lt": stamp}},
                    {"timestamp": stamp, "_id": {"$lt": scene_id}}]}]}
            found = store.scenes.find(query, LIST_FIELDS).sort(
                [("timestamp", DESCENDING), ("_id", DESCENDING)]).limit(SCENES_PER_PAGE + 1)
            return list(found)

        choices, query = await run_in_threadpool(choose)
        if type:  # shown chosen as stored (`Logo` is pm.annotation.Logo)
            filters["type"] = query[CHOICES["type"]]
        # the counts, the histogram and the page at once: each its own commands, each within
        # its own time budget, so the page waits for the slowest, not for their sum
        scenes, counts, histogram = await asyncio.gather(
            run_in_threadpool(listed, query),
            run_in_threadpool(facet_counts, store.scenes, query, choices, CHOICES),
            run_in_threadpool(scene_histogram, store.scenes, query))
        given = {name: value for name, value in filters.items() if value}
        older = None
        if len(scenes) > SCENES_PER_PAGE:
            scenes = scenes[:SCENES_PER_PAGE]
            last = scenes[-1]
            older = {**given, "before": f"{last['timestamp']}-{last['_id']}"}
        return page(request, "scenes.html", {
            "scenes": scenes, "choices": choices, "older": older, "filters": filters,
            "given": given, "counts": counts, "shown": shown, "histogram": histogram,
            "time_inputs": {name: time_input_type(filters[name]) for name in ("since", "until")},
            "bar_links": histogram and [_link(given, bar) for bar in histogram.bars],
        }, policy=SCRIPT_CSP)  # the histogram's brushing (static/brush.js)

    return router


def _link(given: dict[str, str], bar: Bar) -> str:
    """The scene log with the same filters over the time of one bar of its histogram."""
    return "/scenes?" + urlencode({**given, "since": bar.since, "until": bar.until})


def scene_filter(filters: dict[str, str], stored_types: list[str]) -> dict:
    """The MongoDB filter of the scene log's URL parameters (values, never operators)."""
    query: dict = {CHOICES[name]: filters[name] for name in ("robot", "region", "annotator")
                   if filters[name]}
    if filters["type"]:
        query[CHOICES["type"]] = annotation_type(filters["type"], stored_types)
    span = {op: read(filters[name], name) for op, name, read in (
        ("$gte", "since", nanoseconds), ("$lt", "until", nanoseconds_through)) if filters[name]}
    if span:
        query["timestamp"] = span
    return query


def annotation_type(text: str, stored: list[str]) -> str:
    """The stored name of an annotation type: one stored (also unknown ones), or a registered
    one by its name, an alias (rs.annotation.Classification) or its short name (Logo), as
    the query model's field predicates take them."""
    if text in stored:
        return text
    try:
        return canonical_type(text)
    except ValueError as error:
        raise PageError(422, f"type: {error}") from None


def _cursor(text: str) -> tuple[int, ObjectId]:
    stamp, _, scene_id = text.partition("-")
    digits = stamp.isascii() and stamp.isdigit()
    if not digits or not ObjectId.is_valid(scene_id) or int(stamp) >= 2**63:
        raise PageError(422, f"before: {text!r} is not a page cursor (<timestamp>-<scene id>)")
    return int(stamp), ObjectId(scene_id)
