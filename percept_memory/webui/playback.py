"""The playback page: a robot's scenes, in one map or in all, as a sequence
(queries/playback.py; GET /api/playback is its JSON twin). It shows one scene, its image or its
clusters' crops, beside the belief of its map at the scene's time, under a timeline: a time
slider, steps to the first, previous, next and last scene, to the next scene where an
annotator failed, and to the next event of an object the user follows. The steps are plain
links, worked out when the page is made, so the page plays without JavaScript, one page at a
time; static/playback.js steps without reloading and plays the sequence on.
"""

from __future__ import annotations

from dataclasses import dataclass

from bson import ObjectId
from fastapi import APIRouter, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import HTMLResponse
from pydantic import ValidationError
from pymongo import DESCENDING

from percept_memory.memory.errors import NotFound
from percept_memory.memory.schema import EVENTS, OBJECTS
from percept_memory.memory.store import MemoryStore
from percept_memory.queries.engine import QueryEngine
from percept_memory.queries.model import Playback
from percept_memory.queries.ops import QueryError
from percept_memory.queries.results import Frame

from .belief_map import SECOND, drawn_belief, map_names, moment_of, recorded_span
from .html import SCRIPT_CSP, PageError, page, parse_id

MARKS = 500  # of each kind on the timeline: the sequence's first failures, the object's events
STRIP = 1000  # the timeline's width, in its drawing's units


@dataclass
class Mark:
    """A failure, or an event of the followed object, at x along the sequence's time."""

    kind: str  # failure | event
    t: int
    x: float


def routes(store: MemoryStore, engine: QueryEngine) -> APIRouter:
    router = APIRouter(include_in_schema=False, default_response_class=HTMLResponse)

    @router.get("/playback")
    async def playback_page(request: Request, robot: str = "", map: str = "", t: str = "",
                            at: str = "", object: str = "") -> HTMLResponse:
        moment = moment_of(t, at)
        followed = parse_id(object, "object") if object.strip() else None
        robots = await run_in_threadpool(_robots, store)
        if not robots:
            return page(request, "playback.html", {"frame": None}, policy=SCRIPT_CSP)
        chosen = robot or await run_in_threadpool(_newest_robot, store)
        if chosen not in robots:
            raise PageError(404, f"no scenes of a robot named {chosen!r}")
        if followed and not await run_in_threadpool(store.objects.find_one, {"_id": followed},
                                                    {"_id": 1}):
            raise PageError(404, f"no object {followed} to follow")
        try:
            asked = Playback(robot=chosen, map=map or None, t=moment)
        except ValidationError as error:
            raise PageError(422, "the moment asked for is not valid", [
                f"{'.'.join(str(part) for part in e['loc'])}: {e['msg']}"
                for e in error.errors()]) from None

        def load() -> dict:
            frame = engine.playback(asked)
            scene = store.get_scene(frame.scene_id)
            shown = [c.object_id for c in scene.clusters if c.object_id]
            return {
                "frame": frame, "scene": scene, "robots": robots,
                "maps": sorted({*map_names(store), frame.map}),
                "sequence": asked, "followed": followed,
                "kept": {k: v for k, v in (("map", map), ("object", followed)) if v},
                "names": _names(store, [*shown, followed]),
                "failure": _step(engine, asked, frame, "failure"),
                "previous_failure": _step(engine, asked, frame, "previous_failure"),
                "event": followed and _step(engine, asked, frame, "event", followed),
                "belief": drawn_belief(store, engine, frame.map, frame.time,
                                       recorded_span(store, frame.map)[0]),
                "marks": _marks(store, asked, frame, followed), "strip": STRIP,
                "second": SECOND,
            }

        try:
            context = await run_in_threadpool(load)
        except NotFound as error:  # no scenes of the robot in that map
            raise PageError(404, str(error)) from None
        except QueryError as error:
            raise PageError(503, str(error)) from None
        return page(request, "playback.html", context, policy=SCRIPT_CSP)

    return router


def _step(engine: QueryEngine, asked: Playback, frame: Frame, step: str,
          followed: ObjectId | None = None) -> int | None:
    """The time of the scene a step from this frame goes to, or None if there is none."""
    try:
        return engine.playback(asked.model_copy(
            update={"t": frame.time, "step": step, "object": followed})).time
    except NotFound:
        return None


def _marks(store: MemoryStore, asked: Playback, frame: Frame,
           followed: ObjectId | None) -> list[Mark]:
    """Where the sequence's failures (by the partial index of failing scenes) and the followed
    object's events in it are along its time, for the timeline to show and lead to."""
    sequence = {"robot": asked.robot, **({"map": asked.map} if asked.map else {})}
    found = [("failure", d["timestamp"]) for d in store.scenes.find(
        {**sequence, "log.level": "error"}, {"timestamp": 1},
        sort=[("robot", 1), ("timestamp", 1)], limit=MARKS)]
    if followed:
        found += [("event", e["time"]) for e in store.db[EVENTS].find(
            {"object_id": followed, **sequence}, {"time": 1},
            sort=[("object_id", 1), ("time", 1)], limit=MARKS)]
    span = max(frame.last - frame.first, 1)
    return [Mark(kind, t, round((t - frame.first) / span * STRIP, 1)) for kind, t in found]


def _robots(store: MemoryStore) -> list[str]:
    return sorted(store.scenes.distinct("robot"))


def _newest_robot(store: MemoryStore) -> str:
    return store.scenes.find_one({}, {"robot": 1}, sort=[("timestamp", DESCENDING)])["robot"]


def _names(store: MemoryStore, ids: list) -> dict:
    """The objects' names by id, in the order given (None: no name), for the follow list."""
    found = {o["_id"]: o.get("name") for o in store.db[OBJECTS].find(
        {"_id": {"$in": [i for i in ids if i]}}, {"name": 1})}
    return {i: found[i] for i in ids if i in found}
