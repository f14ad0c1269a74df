"""The object page: what the memory believes about one physical object and how it came to
believe it (consolidation.py: its `objects` document and its `events`). Its names and state;
its track, the positions of its events in time order drawn on the map's floor plan
(belief_map.floor_plan); its history as a timeline of bars, one per event, as tall as the
event's probability and coloured by its explanation (appear, stay, move, newview, hidden,
disappear); its crops over time; and the events as a table. The latest EVENTS_SHOWN events.
"""

from __future__ import annotations

from dataclasses import dataclass

from bson import ObjectId
from fastapi import APIRouter, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import HTMLResponse, RedirectResponse, Response
from pymongo import DESCENDING

from percept_memory.memory.pipeline import rebuilding
from percept_memory.memory.schema import EVENTS, OBJECTS
from percept_memory.memory.store import MemoryStore
from percept_memory.queries.results import position_sigma

from . import curation
from .belief_map import Projection, floor_plan
from .html import SCRIPT_CSP, PageError, page, parse_id

EVENTS_SHOWN = 500
TIMELINE_WIDTH, TIMELINE_HEIGHT, TIMELINE_MARGIN = 960, 80, 8
TRACK_WIDTH, TRACK_HEIGHT = 480, 400


@dataclass
class Mark:
    """An event drawn at (x, y) in its drawing's pixels."""

    event: dict
    x: float
    y: float


@dataclass
class Timeline:
    """The events along time, left to right; a bar's height is the event's probability."""

    bars: list[Mark]  # y is the top of the bar
    first: int
    last: int
    width: int = TIMELINE_WIDTH
    height: int = TIMELINE_HEIGHT
    baseline: int = TIMELINE_HEIGHT - TIMELINE_MARGIN  # where bars stand


def routes(store: MemoryStore) -> APIRouter:
    router = APIRouter(include_in_schema=False, default_response_class=HTMLResponse)
    objects, events = store.db[OBJECTS], store.db[EVENTS]

    @router.get("/objects/{object_id}")
    async def object_page(request: Request, object_id: str) -> Response:
        key = parse_id(object_id, "object")

        def load():
            believed = objects.find_one({"_id": key})
            if believed is None:  # an object is named by its first observation: merged into
                now = store.clusters.find_one({"_id": key}, {"object_id": 1, "search.map": 1})
                if now is not None and now.get("object_id") not in (None, key):  # another
                    return now["object_id"]
                map_name = now and now.get("search", {}).get("map")
                if map_name and rebuilding(store.db, map_name):  # (its clusters still name it)
                    raise PageError(404, f"object {key} is not in the belief now: the belief of "
                                         f"map {map_name} is being rebuilt; reload in a moment")
                raise PageError(404, f"no object {key}")
            history = list(events.find({"object_id": key}).sort("time", DESCENDING)
                           .limit(EVENTS_SHOWN))
            placed = [e for e in reversed(history) if e.get("position")]
            view, regions = floor_plan(store, believed.get("map"), [e["position"] for e in placed],
                                       TRACK_WIDTH, TRACK_HEIGHT)
            candidates = curation.merge_candidates(store, believed, history)
            return (believed, history, view, regions, track(view, placed), candidates,
                    bool(rebuilding(store.db, believed.get("map"))))

        loaded = await run_in_threadpool(load)
        if isinstance(loaded, ObjectId):
            return RedirectResponse(f"/objects/{loaded}", status_code=303)
        believed, history, view, regions, marks, candidates, being_rebuilt = loaded
        return page(request, "object.html", {
            "object": believed, "events": history, "events_shown": EVENTS_SHOWN,
            "view": view, "regions": regions, "track": marks, "timeline": timeline(history),
            "merge_candidates": candidates, "position_sigma": position_sigma(believed),
            "rebuilding": being_rebuilt,
        }, policy=SCRIPT_CSP)  # its correction form's script (curation.py)

    return router


def track(view: Projection, placed: list[dict]) -> list[Mark]:
    """The events with a position, oldest first, where the floor plan draws them."""
    return [Mark(e, *view.point(e["position"][0], e["position"][1])) for e in placed]


def timeline(history: list[dict]) -> Timeline | None:
    """The events as bars along their time span (one event: in the middle)."""
    if not history:
        return None
    first, last = min(e["time"] for e in history), max(e["time"] for e in history)
    inner = TIMELINE_WIDTH - 2 * TIMELINE_MARGIN
    tall = TIMELINE_HEIGHT - 2 * TIMELINE_MARGIN
    bars = []
    for event in reversed(history):
        share = (event["time"] - first) / (last - first) if last > first else 0.5
        bars.append(Mark(event, round(TIMELINE_MARGIN + share * inner, 1),
                         round(TIMELINE_MARGIN + (1 - event["probability"]) * tall, 1)))
    return Timeline(bars, first, last)
