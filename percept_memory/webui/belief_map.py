"""The map page: a top-down SVG of the regions and of the objects believed there at any moment
(QueryEngine.what_is_at: an object's belief at t is its last event at or before t), present
objects solid, hidden ones (out of view, still believed there) dashed, grey and the fainter
the longer ago they were last seen, each a link to its page. Labels never overlap: an object
whose name finds no free place beside it (layout.py) is counted in a marker of its crowd,
named in the marker's tooltip and in the table below. The moment is `t` (nanoseconds since
the epoch or ISO 8601, as in the query model) or `at`, whole seconds since the epoch: the time
slider's value, since a browser sends a range input's large values in exponent form. A plain
GET form with the slider picks the moment; links step to the scene before and after it, and
to the round times of a time axis under the slider (time_axis.py).

The page shows one map at a time (`map`, default: the map of the newest scene), chosen from a
list: regions, objects and the belief are per map. The store keeps no outlines of regions, so
a region is drawn as the box around the positions of the map's objects last seen in it.
With `view=3d` the page adds the same in 3D (scene3d.py); the playback page draws the belief
of its scene's moment as this page does (drawn_belief).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

from fastapi import APIRouter, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import HTMLResponse
from pydantic import TypeAdapter, ValidationError
from pymongo import ASCENDING, DESCENDING

from percept_memory.memory.schema import EVENTS, MAPS, OBJECTS
from percept_memory.memory.store import MemoryStore
from percept_memory.queries.engine import QueryEngine
from percept_memory.queries.model import Time
from percept_memory.queries.ops import QueryError
from percept_memory.queries.results import ObjectAt

from . import scene3d, time_axis
from .html import CSP, SCRIPT_CSP, PageError, bounded_int, page
from .layout import RINGS, Box, Label, Layout

SECOND = 1_000_000_000
MAX_REGIONS = 500
WIDTH, MAX_HEIGHT, MARGIN, PAD_M = 960, 720, 24, 0.15
FONT, RADIUS = 11, 6  # px: the labels' size (style.css: .map text) and the objects' dots'
CROWD = 40  # px: objects without a label this near the crowd's first are counted with it
# labels tried at most, in order (present, then the latest seen): more names than this are
# unreadable anyway, and each that finds no room costs dozens of overlap tests (a map of
# 10,000 objects took 2.4 s); the rest are counted in their crowds
LABELS_TRIED = 300
FAINTEST = 0.25  # the opacity of a hidden object last seen at the map's first scene
AGE_UNIT = 60 * SECOND  # ages count on a logarithmic scale from about this
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
        scale = min((width - 2 * MARGIN) / _half(x1, x0),
                    (max_height - 2 * MARGIN) / _half(y1, y0)) / 2
        return cls(x0, y1, scale, round(_half(x1, x0) * scale * 2 + 2 * MARGIN),
                   round(_half(y1, y0) * scale * 2 + 2 * MARGIN))

    def point(self, x: float, y: float) -> tuple[float, float]:
        return (round(MARGIN + _half(x, self.x0) * self.scale * 2, 1),
                round(MARGIN + _half(self.y1, y) * self.scale * 2, 1))


def _half(a: float, b: float) -> float:
    """(a - b) / 2, exactly, but finite for any finite a and b: positions may lie as far apart
    as floats go, and 1e308 - -1e308 overflows."""
    return a / 2 - b / 2


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
    opacity: float = 1.0
    label: Label | None = None


@dataclass
class Crowd:
    """Objects near each other whose labels found no free place: one counted marker."""

    objects: list[DrawnObject]
    label: Label | None = None

    @property
    def names(self) -> str:
        return ", ".join(o.belief.name or "unnamed object" for o in self.objects)


@dataclass
class DrawnBelief:
    """The objects believed in a map at a moment, drawn on its floor plan with labels that
    never overlap (macros.html: belief_figure); those without a position listed apart."""

    view: Projection
    regions: list[DrawnRegion]
    region_labels: dict[str, Label]
    objects: list[DrawnObject]
    crowds: list[Crowd]
    unplaced: list[ObjectAt]

    @property
    def believed(self) -> list[ObjectAt]:
        return [o.belief for o in self.objects] + self.unplaced


def drawn_belief(store: MemoryStore, engine: QueryEngine, map_name: str, t: int,
                 start: int) -> DrawnBelief:
    """What the map page and the playback draw: QueryEngine.what_is_at on the floor plan,
    labelled (lay_out), hidden objects fading with their age since start, the map's first
    scene."""
    believed = engine.what_is_at(map=map_name, t=t).objects
    placed = [o for o in believed if o.position is not None]
    view, regions = floor_plan(store, map_name, [o.position for o in placed])
    seen = _last_seen(store, [o.object_id for o in placed if o.state == "hidden"], t)
    objects = [DrawnObject(o, *view.point(o.position[0], o.position[1]),
                           _opacity(seen.get(o.object_id), start, t)) for o in placed]
    region_labels, crowds = lay_out(view, regions, objects)
    return DrawnBelief(view, regions, region_labels, objects, crowds,
                       [o for o in believed if o.position is None])


def routes(store: MemoryStore, engine: QueryEngine) -> APIRouter:
    router = APIRouter(include_in_schema=False, default_response_class=HTMLResponse)

    @router.get("/map")
    async def map_page(request: Request, map: str = "", t: str = "", at: str = "",
                       view: str = "") -> HTMLResponse:
        in_3d = scene3d.wanted(view)
        maps = await run_in_threadpool(map_names, store)
        if not maps:
            return page(request, "map.html", {"span": None})
        chosen = map or await run_in_threadpool(_newest_map, store)
        if chosen not in maps:
            raise PageError(404, f"no map named {chosen!r}")
        span = await run_in_threadpool(recorded_span, store, chosen)
        moment = moment_of(t, at) or span[1]

        def load():
            belief = drawn_belief(store, engine, chosen, moment, span[0])
            solid = scene3d.map_view(region_boxes(store, chosen),
                                     belief.believed) if in_3d else None
            return belief, _neighbours(store, chosen, moment), solid

        try:
            belief, (earlier, later), solid = await run_in_threadpool(load)
        except QueryError as error:
            raise PageError(503, str(error)) from None
        return page(request, "map.html", {
            "maps": maps, "map": chosen, "span": span, "t": moment, "belief": belief,
            "axis": time_axis.axis(*span, moment, WIDTH),
            "earlier": earlier, "later": later, "second": SECOND, "view3d": solid,
        }, policy=SCRIPT_CSP if in_3d else CSP)

    return router


def floor_plan(store: MemoryStore, map_name: str | None, positions: list, width: int = WIDTH,
               max_height: int = MAX_HEIGHT) -> tuple[Projection, list[DrawnRegion]]:
    """The map's regions drawn top-down, in a projection that holds them and these positions
    (metres: x, y and any more coordinates) in at most width x max_height pixels. The map page
    and the object page's track draw on it (macros.html: floor_plan)."""
    boxes = region_boxes(store, map_name)
    xs = [x for low, high in boxes.values() for x in (low[0], high[0])]
    ys = [y for low, high in boxes.values() for y in (low[1], high[1])]
    view = Projection.around(xs + [p[0] for p in positions], ys + [p[1] for p in positions],
                             width, max_height)
    regions = []
    for name, (low, high) in sorted(boxes.items()):
        (left, top), (right, bottom) = view.point(low[0], high[1]), view.point(high[0], low[1])
        regions.append(DrawnRegion(name, left, top, right - left, bottom - top))
    return view, regions


def lay_out(view: Projection, regions: list[DrawnRegion],
            objects: list[DrawnObject]) -> tuple[dict[str, Label], list[Crowd]]:
    """Labels that never overlap: the regions' names first, then the objects' (present ones
    first, then hidden ones, the most recently seen first; LABELS_TRIED at most). The objects
    left without a label are counted in one marker per crowd (layout.py)."""
    drawing = Layout(view.width, view.height, FONT)
    for o in objects:
        drawing.block(Box(o.x - RADIUS, o.y - RADIUS, 2 * RADIUS, 2 * RADIUS))
    height = FONT * 1.2
    region_labels = {}
    for r in regions:  # inside its top left corner, above it, inside its foot, below it
        corners = ((r.x + 4, r.y + 2), (r.x, r.y - height - 2),
                   (r.x + 4, r.y + r.height - height - 2), (r.x, r.y + r.height + 2))
        if label := drawing.place_at(r.name, corners):
            region_labels[r.name] = label
    crowds: list[Crowd] = []
    by_cell: dict[tuple[int, int], list] = {}  # (n, crowd) by its first object's cell
    widest = f"+{len(objects)}"  # a marker's room, taken when its crowd begins
    ordered = sorted(objects, key=lambda o: (o.belief.state != "present", -o.opacity))
    for tried, o in enumerate(ordered):
        o.label = (drawing.place(o.belief.name or "?", o.x, o.y, RADIUS)
                   if tried < LABELS_TRIED else None)
        if o.label is not None:
            continue
        cx, cy = int(o.x // CROWD), int(o.y // CROWD)
        near = min(((n, c) for i in (-1, 0, 1) for j in (-1, 0, 1)
                    for n, c in by_cell.get((cx + i, cy + j), ())
                    if abs(c.objects[0].x - o.x) <= CROWD and abs(c.objects[0].y - o.y) <= CROWD),
                   key=lambda found: found[0], default=None)
        if near is None:
            crowd = Crowd([o], drawing.place(widest, o.x, o.y, RADIUS, 2 * RINGS))
            by_cell.setdefault((cx, cy), []).append((len(crowds), crowd))
            crowds.append(crowd)
        else:
            near[1].objects.append(o)
    for crowd in crowds:
        if crowd.label is not None:  # the count, within the room taken
            count = f"+{len(crowd.objects)}"
            crowd.label = replace(crowd.label, text=count, box=replace(
                crowd.label.box, width=drawing.text_width(count)))
    return region_labels, crowds


def _opacity(last_seen: int | None, start: int, t: int) -> float:
    """How opaque a hidden object is drawn: 1 if seen just now, down to FAINTEST if last seen
    at the map's first scene, by the logarithm of its age, so that minutes, hours and days
    look apart in a map of a day as in one of a year. Present objects (None) are opaque."""
    if last_seen is None or t <= start:
        return 1.0
    age = math.log1p(max(0, t - last_seen) / AGE_UNIT) / math.log1p((t - start) / AGE_UNIT)
    return round(1 - (1 - FAINTEST) * min(1.0, age), 2)


def _last_seen(store: MemoryStore, object_ids: list, t: int) -> dict:
    """Per object, the time it was last seen (not hidden, not gone) up to t."""
    found = store.db[EVENTS].aggregate([
        {"$match": {"object_id": {"$in": object_ids}, "time": {"$lte": t},
                    "explanation": {"$nin": ["hidden", "disappear"]}}},
        {"$group": {"_id": "$object_id", "time": {"$max": "$time"}}},
    ])
    return {doc["_id"]: doc["time"] for doc in found}


def moment_of(t: str, at: str) -> int | None:
    """The moment the URL asks for, if any."""
    if t.strip() and at.strip():
        raise PageError(422, "give t or at, not both")
    if at.strip():
        return bounded_int(at, "at", 0, (2**63 - 1) // SECOND) * SECOND
    try:
        return time_of_text.validate_python(t) if t.strip() else None
    except ValidationError as error:
        raise PageError(422, f"t: {error.errors()[0]['msg']}") from None


def map_names(store: MemoryStore) -> list[str]:
    """The maps with a belief, by name."""
    return sorted(store.db[MAPS].distinct("_id"))


def _newest_map(store: MemoryStore) -> str | None:
    newest = store.scenes.find_one({}, {"map": 1}, sort=[("timestamp", DESCENDING)])
    return newest and newest.get("map")


def recorded_span(store: MemoryStore, map_name: str) -> tuple[int, int]:
    """The first and the last scene's time of the map, to whole seconds (the slider's ends)."""
    first, last = (store.scenes.find_one({"map": map_name}, {"timestamp": 1},
                                         sort=[("map", 1), ("timestamp", order)])
                   for order in (ASCENDING, DESCENDING))
    if first is None:
        return 0, 0
    return (first["timestamp"] // SECOND * SECOND,
            -(-last["timestamp"] // SECOND) * SECOND)


def _neighbours(store: MemoryStore, map_name: str, t: int) -> tuple[int | None, int | None]:
    """The times of the map's scenes just before and just after t."""
    before = store.scenes.find_one({"map": map_name, "timestamp": {"$lt": t}}, {"timestamp": 1},
                                   sort=[("map", 1), ("timestamp", DESCENDING)])
    after = store.scenes.find_one({"map": map_name, "timestamp": {"$gt": t}}, {"timestamp": 1},
                                  sort=[("map", 1), ("timestamp", ASCENDING)])
    return (before and before["timestamp"]), (after and after["timestamp"])


def region_boxes(store: MemoryStore,
                 map_name: str | None) -> dict[str, tuple[list[float], list[float]]]:
    """Per region of the map, the (x, y, z) box around its objects last seen there (by the
    objects' map index), widened by PAD_M on the ground; z is 0 for positions without one."""
    z = {"$ifNull": [{"$arrayElemAt": ["$position", 2]}, 0.0]}
    found = store.db[OBJECTS].aggregate([
        {"$match": {"map": map_name, "region": {"$type": "string"}, "x": {"$ne": None}}},
        {"$group": {"_id": "$region", "x0": {"$min": "$x"}, "y0": {"$min": "$y"},
                    "z0": {"$min": z}, "x1": {"$max": "$x"}, "y1": {"$max": "$y"},
                    "z1": {"$max": z}}},
        {"$sort": {"_id": 1}},
        {"$limit": MAX_REGIONS},
    ])
    return {b["_id"]: ([b["x0"] - PAD_M, b["y0"] - PAD_M, b["z0"]],
                       [b["x1"] + PAD_M, b["y1"] + PAD_M, b["z1"]]) for b in found}
