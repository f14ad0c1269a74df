"""The map page: a top-down SVG of the regions and of the objects believed there at any moment
(QueryEngine.what_is_at: an object's belief at t is its last event at or before t), present
objects solid, hidden ones (out of view, still believed there) dashed and grey, each a link
to its page and labelled with its name. The moment is `t` (nanoseconds since the epoch or ISO
8601, as in the query model) or `at`, whole seconds since the epoch: the time slider's value,
since a browser sends a range input's large values in exponent form. A plain GET form with the
slider picks the moment; links step to the scene before and after it.

The store keeps no outlines of regions, so a region is drawn as the box around the positions
of its most recent observations (REGION_SAMPLE clusters each, by the region index).
"""

from __future__ import annotations

from dataclasses import dataclass

from fastapi import APIRouter, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import HTMLResponse
from pydantic import TypeAdapter, ValidationError
from pymongo import ASCENDING, DESCENDING

from percept_memory.memory.schema import PLACE_LIMIT_M
from percept_memory.memory.store import MemoryStore
from percept_memory.queries.engine import QueryEngine
from percept_memory.queries.model import Box, Time
from percept_memory.queries.ops import QueryError
from percept_memory.queries.results import ObjectAt

from .html import PageError, bounded_int, page

SECOND = 1_000_000_000
EVERYWHERE = Box(low=(-PLACE_LIMIT_M,) * 3, high=(PLACE_LIMIT_M,) * 3)
REGION_SAMPLE = 200
MAX_REGIONS = 500
WIDTH, MAX_HEIGHT, MARGIN, PAD_M = 960, 720, 24, 0.15
time_of_text = TypeAdapter(Time)


@dataclass
class Projection:
    """Map metres to SVG pixels, north up, the whole extent in at most WIDTH x MAX_HEIGHT."""

    x0: float
    y1: float
    scale: float
    width: int
    height: int

    @classmethod
    def around(cls, xs: list[float], ys: list[float], width: int = WIDTH,
               max_height: int = MAX_HEIGHT) -> Projection:
        x0, x1 = min(xs, default=0) - PAD_M, max(xs, default=1) + PAD_M
        y0, y1 = min(ys, default=0) - PAD_M, max(ys, default=1) + PAD_M
        scale = min((width - 2 * MARGIN) / (x1 - x0), (max_height - 2 * MARGIN) / (y1 - y0))
        return cls(x0, y1, scale, round((x1 - x0) * scale + 2 * MARGIN),
                   round((y1 - y0) * scale + 2 * MARGIN))

    def point(self, x: float, y: float) -> tuple[float, float]:
        return (round(MARGIN + (x - self.x0) * self.scale, 1),
                round(MARGIN + (self.y1 - y) * self.scale, 1))


@dataclass
class DrawnRegion:
    name: str
    x: float
    y: float
    width: float
    height: float


@dataclass
class DrawnObject:
    belief: ObjectAt
    x: float
    y: float


def routes(store: MemoryStore, engine: QueryEngine) -> APIRouter:
    router = APIRouter(include_in_schema=False, default_response_class=HTMLResponse)

    @router.get("/map")
    async def map_page(request: Request, t: str = "", at: str = "") -> HTMLResponse:
        span = await run_in_threadpool(_recorded_span, store)
        if span is None:
            return page(request, "map.html", {"span": None})
        moment = _moment(t, at) or span[1]

        def load():
            believed = engine.what_is_at(box=EVERYWHERE, t=moment).objects
            placed = [o for o in believed if o.position is not None]
            return believed, placed, floor_plan(store, [o.position for o in placed]), \
                _neighbours(store, moment)

        try:
            believed, placed, (view, regions), (earlier, later) = await run_in_threadpool(load)
        except QueryError as error:
            raise PageError(503, str(error)) from None
        objects = [DrawnObject(o, *view.point(o.position[0], o.position[1])) for o in placed]
        return page(request, "map.html", {
            "span": span, "t": moment, "view": view, "regions": regions, "objects": objects,
            "unplaced": [o for o in believed if o.position is None],
            "earlier": earlier, "later": later, "second": SECOND,
        })

    return router


def floor_plan(store: MemoryStore, positions: list, width: int = WIDTH,
               max_height: int = MAX_HEIGHT) -> tuple[Projection, list[DrawnRegion]]:
    """The regions drawn top-down, in a projection that holds them and these positions (map
    frame, metres: x, y and any more coordinates) in at most width x max_height pixels. The
    map page and the object page's track draw on it (macros.html: floor_plan)."""
    boxes = _region_boxes(store)
    xs = [x for low, high in boxes.values() for x in (low[0], high[0])]
    ys = [y for low, high in boxes.values() for y in (low[1], high[1])]
    view = Projection.around(xs + [p[0] for p in positions], ys + [p[1] for p in positions],
                             width, max_height)
    regions = []
    for name, (low, high) in sorted(boxes.items()):
        (left, top), (right, bottom) = view.point(low[0], high[1]), view.point(high[0], low[1])
        regions.append(DrawnRegion(name, left, top, right - left, bottom - top))
    return view, regions


def _moment(t: str, at: str) -> int | None:
    """The moment the URL asks for, if any."""
    if t.strip() and at.strip():
        raise PageError(422, "give t or at, not both")
    if at.strip():
        return bounded_int(at, "at", 0, (2**63 - 1) // SECOND) * SECOND
    try:
        return time_of_text.validate_python(t) if t.strip() else None
    except ValidationError as error:
        raise PageError(422, f"t: {error.errors()[0]['msg']}") from None


def _recorded_span(store: MemoryStore) -> tuple[int, int] | None:
    """The first and the last scene's time, to whole seconds (the slider's ends)."""
    first = store.scenes.find_one({}, {"timestamp": 1}, sort=[("timestamp", ASCENDING)])
    last = store.scenes.find_one({}, {"timestamp": 1}, sort=[("timestamp", DESCENDING)])
    if first is None:
        return None
    return (first["timestamp"] // SECOND * SECOND,
            -(-last["timestamp"] // SECOND) * SECOND)


def _neighbours(store: MemoryStore, t: int) -> tuple[int | None, int | None]:
    """The times of the scenes just before and just after t."""
    before = store.scenes.find_one({"timestamp": {"$lt": t}}, {"timestamp": 1},
                                   sort=[("timestamp", DESCENDING)])
    after = store.scenes.find_one({"timestamp": {"$gt": t}}, {"timestamp": 1},
                                  sort=[("timestamp", ASCENDING)])
    return (before and before["timestamp"]), (after and after["timestamp"])


def _region_boxes(store: MemoryStore) -> dict[str, tuple[list[float], list[float]]]:
    """Per region, the (x, y) box around the positions of its latest observations."""
    boxes = {}
    regions = [r for r in store.clusters.distinct("search.region") if r][:MAX_REGIONS]
    for region in regions:
        found = list(store.clusters.aggregate([
            {"$match": {"search.region": region}},
            {"$sort": {"search.time": -1, "_id": -1}},
            {"$limit": REGION_SAMPLE},
            {"$match": {"search.position": {"$type": "array"}}},
            {"$group": {"_id": None,
                        "x0": {"$min": {"$arrayElemAt": ["$search.position", 0]}},
                        "y0": {"$min": {"$arrayElemAt": ["$search.position", 1]}},
                        "x1": {"$max": {"$arrayElemAt": ["$search.position", 0]}},
                        "y1": {"$max": {"$arrayElemAt": ["$search.position", 1]}}}},
        ]))
        if found:
            b = found[0]
            boxes[region] = ([b["x0"] - PAD_M, b["y0"] - PAD_M], [b["x1"] + PAD_M, b["y1"] + PAD_M])
    return boxes
