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

At any density: beyond ONE_BY_ONE objects in view, the drawing is cut into cells and a cell
of more than SPARSE objects draws them as one disc with their count (grid clustering, as
supercluster or FiftyOne's map do), a link to the same page zoomed into their box
(`box=x0,y0,x1,y1`, metres), so a page draws a bounded number of items however many objects
the map holds. Now (the default moment) the belief is read from `objects`, a box by its
map_place index alone; at a past moment it is each object's last event by then, one index
seek per object of the map (an object believed in the box then may be elsewhere now).

The page shows one map at a time (`map`, default: the map of the newest scene), chosen from a
list: regions, objects and the belief are per map. The store keeps no outlines of regions, so
a region is drawn as the box around the positions of the map's objects last seen in it.
With `view=3d` the page adds the same in 3D (scene3d.py); the playback page draws the belief
of its scene's moment as this page does (drawn_belief).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import TypeVar

from fastapi import APIRouter, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import HTMLResponse
from pydantic import TypeAdapter, ValidationError
from pymongo import ASCENDING, DESCENDING

from percept_memory.memory.pipeline import rebuilding
from percept_memory.memory.schema import EVENTS, MAPS, OBJECTS
from percept_memory.memory.store import MemoryStore
from percept_memory.queries.engine import QueryEngine
from percept_memory.queries.model import Place, Time
from percept_memory.queries.ops import Find, Plan, QueryError
from percept_memory.queries.questions import latest_events, names_of, object_at
from percept_memory.queries.results import ObjectAt

from . import scene3d, time_axis
from .html import CSP, SCRIPT_CSP, PageError, bounded_int, page
from .layout import CHAR_WIDTH, RINGS, Box, Label, Layout

SECOND = 1_000_000_000
MAX_REGIONS = 500
WIDTH, MAX_HEIGHT, MARGIN, PAD_M = 960, 720, 24, 0.15
FONT, RADIUS = 11, 6  # px: the labels' size (style.css: .map text) and the objects' dots'
MARKER_FONT = 10  # px: the size of a marker's count (style.css: .map .marker text)
CROWD = 40  # px: objects without a label this near the crowd's first are counted with it
# labels tried at most, in order (present, then the latest seen): more names than this are
# unreadable anyway, and each that finds no room costs dozens of overlap tests (a map of
# 10,000 objects took 2.4 s); the rest are counted in their crowds
LABELS_TRIED = 300
FAINTEST = 0.25  # the opacity of a hidden object last seen at the map's first scene
AGE_UNIT = 60 * SECOND  # ages count on a logarithmic scale from about this
# the drawing's cells (px): one holding more than SPARSE objects draws them as one counted
# marker, so a page draws at most SPARSE * 17 * 13 objects and markers, however many there are
CELL, SPARSE = 60, 3
ONE_BY_ONE = 200  # objects in view drawn one by one whatever their density (labels or crowds)
MIN_SPAN_M = 0.05  # the narrowest view a marker leads to: objects nearer are one spot
# what an event tells of the belief it made (queries.results.ObjectAt)
OBJECT_AT_FIELDS = {key: 1 for key in ("object_id", "map", "explanation", "region", "position",
                                       "time", "cluster_id")}
time_of_text = TypeAdapter(Time)
T = TypeVar("T")


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
               max_height: int = MAX_HEIGHT, pad: float = PAD_M) -> Projection:
        x0, x1 = min(xs, default=0) - pad, max(xs, default=1) + pad
        y0, y1 = min(ys, default=0) - pad, max(ys, default=1) + pad
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


@dataclass(frozen=True)
class MapBox:
    """The part of a map a zoomed page shows (`box=x0,y0,x1,y1`, metres, edges included)."""

    x0: float
    y0: float
    x1: float
    y1: float

    @classmethod
    def parse(cls, text: str) -> MapBox:
        parts = text.split(",")
        try:
            x0, y0, x1, y1 = (float(p) for p in parts)
        except ValueError:
            raise PageError(422, f"box: {text!r} is not x0,y0,x1,y1 (four numbers, "
                                 "metres)") from None
        if not all(math.isfinite(v) for v in (x0, y0, x1, y1)):
            raise PageError(422, f"box: {text!r} has a coordinate that is not finite")
        if not (x0 < x1 and y0 < y1):
            raise PageError(422, f"box: {text!r} is empty: x0 < x1 and y0 < y1, please")
        return cls(x0, y0, x1, y1)

    @classmethod
    def around(cls, positions: list, margin: float) -> MapBox:
        """The box around these positions, widened by a share of its size, and to at least
        MIN_SPAN_M on each side: a marker's box leads to a view where its objects part."""
        xs, ys = [p[0] for p in positions], [p[1] for p in positions]
        cx, cy = min(xs) / 2 + max(xs) / 2, min(ys) / 2 + max(ys) / 2
        half_x = max(_half(max(xs), min(xs)) * (1 + margin), MIN_SPAN_M / 2)
        half_y = max(_half(max(ys), min(ys)) * (1 + margin), MIN_SPAN_M / 2)
        digits = 2 - math.floor(math.log10(min(half_x, half_y)))  # of a short URL, outward
        return cls(_rounded(cx - half_x, digits, math.floor), _rounded(cy - half_y, digits,
                                                                       math.floor),
                   _rounded(cx + half_x, digits, math.ceil), _rounded(cy + half_y, digits,
                                                                      math.ceil))

    def holds(self, position: list | None) -> bool:
        return (position is not None and self.x0 <= position[0] <= self.x1
                and self.y0 <= position[1] <= self.y1)

    def condition(self) -> dict:
        """The objects whose place (x, y: the map_place index) lies in the box."""
        return {"x": {"$gte": self.x0, "$lte": self.x1}, "y": {"$gte": self.y0, "$lte": self.y1}}

    def __str__(self) -> str:
        return ",".join(repr(v) for v in (self.x0, self.y0, self.x1, self.y1))


def _rounded(value: float, digits: int, direction) -> float:
    """value rounded to `digits` decimals (down: math.floor, up: math.ceil), if finite so."""
    step = 10.0 ** -digits
    rounded = round(direction(value / step) * step, max(digits, 0))
    return rounded if math.isfinite(rounded) else value


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
class Marker:
    """The objects of one dense cell of the drawing, drawn as one disc with their count, as
    large as the count's logarithm, leading to the view of their box."""

    x: float
    y: float
    count: int
    present: int
    box: MapBox

    @classmethod
    def of(cls, members: list[tuple[float, float, dict]]) -> Marker:
        """The marker of one cell's objects at their centre, kept inside the cell so that
        markers never overlap (their radius stays under CELL / 2)."""
        marker = cls(0, 0, len(members), sum(not b["hidden"] for *_, b in members),
                     MapBox.around([b["position"] for *_, b in members], 0.1))
        marker.x, marker.y = (_in_cell([m[axis] for m in members], marker.radius)
                              for axis in (0, 1))
        return marker

    @property
    def radius(self) -> float:
        return round(RADIUS + 3 * math.log10(self.count), 1)

    @property
    def text_width(self) -> float:
        """The count's width, squeezed into the disc."""
        return round(min(len(str(self.count)) * MARKER_FONT * CHAR_WIDTH, 2 * self.radius - 4), 1)

    def blocked(self) -> Box:
        r = self.radius
        return Box(self.x - r, self.y - r, 2 * r, 2 * r)


@dataclass
class DrawnBelief:
    """The objects believed in a map (or in a box of it) at a moment, drawn on its floor plan:
    those of sparse cells one by one with labels that never overlap, the dense cells' as
    counted markers (macros.html: belief_figure); those without a position listed apart."""

    map: str
    view: Projection
    regions: list[DrawnRegion]
    region_labels: dict[str, Label]
    objects: list[DrawnObject]
    crowds: list[Crowd]
    unplaced: list[ObjectAt]
    markers: list[Marker]
    box: MapBox | None
    now: bool  # drawn at the map's newest moment: its links follow the time, not keep it

    @property
    def wider(self) -> MapBox | None:
        """The box twice as wide and high around the same centre (None: the whole map)."""
        if self.box is None:
            return None
        b = self.box
        half_x, half_y = _half(b.x1, b.x0), _half(b.y1, b.y0)
        return MapBox(b.x0 - half_x, b.y0 - half_y, b.x1 + half_x, b.y1 + half_y)

    @property
    def believed(self) -> list[ObjectAt]:
        """The objects drawn one by one, and those without a position."""
        return [o.belief for o in self.objects] + self.unplaced

    @property
    def counted(self) -> int:
        """How many objects the drawing holds, in markers or not."""
        return len(self.objects) + sum(m.count for m in self.markers)


def drawn_belief(store: MemoryStore, engine: QueryEngine, map_name: str, t: int, start: int,
                 box: MapBox | None = None, now: bool = False) -> DrawnBelief:
    """What the map page and the playback draw: the belief at t of the map's objects in the
    box (default: the whole map) on the floor plan; beyond ONE_BY_ONE of them, the objects of
    each cell of the drawing with more than SPARSE as one counted marker; the others labelled
    (lay_out), hidden ones fading with their age since start, the map's first scene. `now`:
    t is at or after the map's newest scene, so the belief is `objects` as it stands
    (believed_now)."""
    if now:
        believed = engine.runner.run(believed_now(map_name, box))
    else:
        believed = [{"object_id": e["object_id"], "position": e.get("position"),
                     "hidden": e["explanation"] == "hidden", "event": e}
                    for e in engine.runner.run(latest_in_map(map_name, t))
                    if box is None or box.holds(e.get("position"))]
    placed = [b for b in believed if b["position"] is not None]
    if box is None:
        view, regions = floor_plan(store, map_name, [b["position"] for b in placed])
    else:
        view = Projection.around([box.x0, box.x1], [box.y0, box.y1], pad=0)
        regions = [r for r in (_clipped(r, view) for r in floor_plan(
            store, map_name, [], view=view)[1]) if r is not None]
    points = [(*view.point(*b["position"][:2]), b) for b in placed]
    single, dense = (points, []) if len(points) <= ONE_BY_ONE else gather(points, CELL, SPARSE)
    listed = [b for _, _, b in single] + [b for b in believed if b["position"] is None]
    if now:  # what made each listed object so: its last event
        by_id = {b["object_id"]: b for b in listed}
        for e in engine.runner.run(latest_events({"$in": list(by_id)}, t,
                                                 fields=OBJECT_AT_FIELDS)):
            by_id[e["object_id"]]["event"] = e
    names = engine.runner.run(names_of([b["object_id"] for b in listed]))
    seen = _last_seen(store, [b["object_id"] for b in listed if b["hidden"]], t)
    objects = [DrawnObject(object_at(b["event"], names), x, y,
                           _opacity(seen.get(b["object_id"]), start, t))
               for x, y, b in single if "event" in b]
    markers = [Marker.of(members) for members in dense]
    region_labels, crowds = lay_out(view, regions, objects, markers)
    return DrawnBelief(map_name, view, regions, region_labels, objects, crowds,
                       [object_at(b["event"], names) for b in listed[len(single):]
                        if "event" in b], markers, box, now)


def believed_now(map_name: str, box: MapBox | None) -> Plan[list[dict]]:
    """The belief now, as `objects` keeps it: each object of the map not gone, at its place
    (the mean of its observations there), by the map_place index (a box: its range alone)."""
    found = yield Find(OBJECTS, {"map": map_name, **(box.condition() if box else {}),
                                 "state": {"$in": ["present", "hidden"]}},
                       {"position": 1, "state": 1})
    return [{"object_id": o["_id"], "position": o.get("position"),
             "hidden": o["state"] == "hidden"} for o in found]


def latest_in_map(map_name: str, t: int) -> Plan[list[dict]]:
    """The belief at t about each of the map's objects (its last event by then, one index
    seek per object) but those gone by then."""
    found = yield Find(OBJECTS, {"map": map_name}, {"_id": 1})
    return (yield from latest_events({"$in": [o["_id"] for o in found]}, t,
                                     Place(map=map_name), OBJECT_AT_FIELDS))


def gather(points: list[tuple[float, float, T]], cell: float,
           sparse: int) -> tuple[list[tuple[float, float, T]], list[list[tuple[float, float, T]]]]:
    """Points (x, y in pixels, item) by square cells of the drawing, as map tools cluster
    theirs (supercluster, FiftyOne's map): those of cells holding at most `sparse` points, and
    the points of each fuller cell together. A w x h drawing thus holds at most
    sparse * (w / cell + 1) * (h / cell + 1) items, however many points there are."""
    cells: dict[tuple[int, int], list] = {}
    for point in points:
        cells.setdefault((int(point[0] // cell), int(point[1] // cell)), []).append(point)
    return ([p for members in cells.values() if len(members) <= sparse for p in members],
            [members for members in cells.values() if len(members) > sparse])


def _in_cell(values: list[float], radius: float) -> float:
    """The mean of a cell's coordinates, moved in so that a disc of this radius there stays
    inside the cell."""
    low = values[0] // CELL * CELL + radius
    return round(min(max(sum(values) / len(values), low), low + CELL - 2 * radius), 1)


def _clipped(r: DrawnRegion, view: Projection) -> DrawnRegion | None:
    """The part of a region inside a zoomed view, or None: the SVG shows what lies beyond."""
    left, top = max(r.x, 0), max(r.y, 0)
    right, bottom = min(r.x + r.width, view.width), min(r.y + r.height, view.height)
    if right <= left or bottom <= top:
        return None
    return DrawnRegion(r.name, left, top, round(right - left, 1), round(bottom - top, 1))


def routes(store: MemoryStore, engine: QueryEngine) -> APIRouter:
    router = APIRouter(include_in_schema=False, default_response_class=HTMLResponse)

    @router.get("/map")
    async def map_page(request: Request, map: str = "", t: str = "", at: str = "",
                       box: str = "", view: str = "") -> HTMLResponse:
        in_3d = scene3d.wanted(view)
        zoomed = MapBox.parse(box) if box else None
        maps = await run_in_threadpool(map_names, store)
        if not maps:
            return page(request, "map.html", {"span": None})
        chosen = map or await run_in_threadpool(_newest_map, store)
        if chosen not in maps:
            raise PageError(404, f"no map named {chosen!r}")
        span = await run_in_threadpool(recorded_span, store, chosen)
        moment = moment_of(t, at) or span[1]

        def load():
            belief = drawn_belief(store, engine, chosen, moment, span[0], zoomed,
                                  now=moment >= span[1])
            solid = scene3d.map_view(region_boxes(store, chosen), engine.what_is_at(
                map=chosen, t=moment).objects) if in_3d else None
            return (belief, _neighbours(store, chosen, moment), solid,
                    rebuilding(store.db, chosen))

        try:
            belief, (earlier, later), solid, being_rebuilt = await run_in_threadpool(load)
        except QueryError as error:
            raise PageError(503, str(error)) from None
        kept = [("map", chosen), *([("box", str(zoomed))] if zoomed else [])]  # by the links
        return page(request, "map.html", {
            "maps": maps, "map": chosen, "kept": kept, "in_view": [("view", "3d")] if in_3d
            else [], "span": span, "t": moment,
            "belief": belief, "axis": time_axis.axis(*span, moment, WIDTH),
            "earlier": earlier, "later": later, "second": SECOND, "view3d": solid,
            "rebuilding": bool(being_rebuilt),
        }, policy=SCRIPT_CSP if in_3d else CSP)

    return router


def floor_plan(store: MemoryStore, map_name: str | None, positions: list, width: int = WIDTH,
               max_height: int = MAX_HEIGHT,
               view: Projection | None = None) -> tuple[Projection, list[DrawnRegion]]:
    """The map's regions drawn top-down, in a projection that holds them and these positions
    (metres: x, y and any more coordinates) in at most width x max_height pixels, or in the
    view given. The map page and the object page's track draw on it (macros.html:
    floor_plan)."""
    boxes = region_boxes(store, map_name)
    if view is None:
        xs = [x for low, high in boxes.values() for x in (low[0], high[0])]
        ys = [y for low, high in boxes.values() for y in (low[1], high[1])]
        view = Projection.around(xs + [p[0] for p in positions], ys + [p[1] for p in positions],
                                 width, max_height)
    regions = []
    for name, (low, high) in sorted(boxes.items()):
        (left, top), (right, bottom) = view.point(low[0], high[1]), view.point(high[0], low[1])
        regions.append(DrawnRegion(name, left, top, right - left, bottom - top))
    return view, regions


def lay_out(view: Projection, regions: list[DrawnRegion], objects: list[DrawnObject],
            markers: list[Marker] = ()) -> tuple[dict[str, Label], list[Crowd]]:
    """Labels that never overlap each other, the objects' dots or the markers: the regions'
    names first, then the objects' (present ones first, then hidden ones, the most recently
    seen first; LABELS_TRIED at most). The objects left without a label are counted in one
    marker per crowd (layout.py)."""
    drawing = Layout(view.width, view.height, FONT)
    for o in objects:
        drawing.block(Box(o.x - RADIUS, o.y - RADIUS, 2 * RADIUS, 2 * RADIUS))
    for marker in markers:
        drawing.block(marker.blocked())
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
    """The maps with a belief or with scenes (the first scenes of a map are stored before the
    consolidator makes its belief: its page was a 404 meanwhile), by name."""
    return sorted({*store.db[MAPS].distinct("_id"), *store.scenes.distinct("map")} - {None})


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
