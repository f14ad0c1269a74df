"""A robot's scenes (in one map, or in all) as a sequence to play back (issue 17, after
FiftyOne's dynamic groups and Foxglove's timeline): the scene shown at a moment, and the steps
a timeline takes from it. Every step is an index seek: on scenes by robot (or map) and time
(a partial index holds only the scenes where an annotator failed), or on events by object and
time.
"""

from __future__ import annotations

from percept_memory.memory.errors import NotFound
from percept_memory.memory.schema import EVENTS, SCENES
from percept_memory.memory.types import iso_from_timestamp

from .model import Playback
from .ops import Find, Plan
from .results import NOW, Frame

FAILED = {"log.level": "error"}  # what schema.py's robot_failed_time index holds
FRAME_FIELDS = {"robot": 1, "map": 1, "timestamp": 1, "summary.clusters": 1, "log.level": 1,
                "log.source": 1}
EVENTS_LOOKED_AT = 50  # the object's next events searched for one in the robot's scenes
FORWARD, BACKWARD = (("robot", 1), ("timestamp", 1)), (("robot", 1), ("timestamp", -1))
BACKWARD_STEPS = ("previous", "previous_failure")


def playback(q: Playback) -> Plan[Frame]:
    """The robot's scene at the moment t, or the step from t the query asks for, with the
    times of the robot's first, previous, next and last scenes."""
    t = NOW if q.t is None else q.t
    sequence = {"robot": q.robot, **({} if q.map is None else {"map": q.map})}
    if q.step == "event":
        found = yield from _event_scene(q, sequence, t)
    else:
        if q.step in BACKWARD_STEPS:  # the step is taken from the scene shown at t
            shown = yield from _scene({**sequence, **_step("at", t)[0]}, BACKWARD,
                                      {"timestamp": 1})
            t = t if shown is None else shown["timestamp"]
        condition, order, wanted = _step(q.step, t)
        found = yield from _scene({**sequence, **condition}, order, FRAME_FIELDS)
        if found is None and q.step == "at":  # before the sequence's first scene: that one
            found = yield from _scene(sequence, FORWARD, FRAME_FIELDS)
        if found is None:
            raise NotFound(_named(q), wanted)
    return (yield from _frame(found, sequence))


def _named(q: Playback) -> str:
    return f"scene of the robot {q.robot!r}" + ("" if q.map is None else f" in map {q.map!r}")


def _step(step: str, t: int) -> tuple[dict, tuple, str]:
    """The condition a step puts on the robot's scenes, their order, and what it looks for."""
    when = "now" if t == NOW else iso_from_timestamp(t)
    if step == "at":
        return {"timestamp": {"$lte": t}}, BACKWARD, f"at or before {when}"
    if step in ("first", "last"):
        return {}, FORWARD if step == "first" else BACKWARD, "at all"
    if step == "previous":
        return {"timestamp": {"$lt": t}}, BACKWARD, f"before {when}"
    if step == "next":
        return {"timestamp": {"$gt": t}}, FORWARD, f"after {when}"
    if step == "previous_failure":
        return ({"timestamp": {"$lt": t}, **FAILED}, BACKWARD,
                f"before {when} where an annotator failed")
    return {"timestamp": {"$gt": t}, **FAILED}, FORWARD, f"after {when} where an annotator failed"


def _scene(condition: dict, order, fields: dict) -> Plan[dict | None]:
    found = yield Find(SCENES, condition, fields, order, 1)
    return found[0] if found else None


def _event_scene(q: Playback, sequence: dict, t: int) -> Plan[dict]:
    """The sequence's first scene after t with an event of the object (seen, moved, found
    hidden or gone), among the object's next EVENTS_LOOKED_AT events."""
    events = yield Find(EVENTS, {"object_id": q.object, "time": {"$gt": t}}, {"scene_id": 1},
                        (("object_id", 1), ("time", 1)), EVENTS_LOOKED_AT)
    found = yield Find(SCENES, {"_id": {"$in": [e["scene_id"] for e in events]}, **sequence},
                       FRAME_FIELDS, (("timestamp", 1),), 1)
    if not found:
        raise NotFound(_named(q), f"after {iso_from_timestamp(t)} with an event of the object "
                                  f"{q.object}")
    return found[0]


def _frame(scene: dict, sequence: dict) -> Plan[Frame]:
    robot, t = scene["robot"], scene["timestamp"]
    times = []
    for step in ("first", "last", "previous", "next"):
        condition, order, _ = _step(step, t)
        found = yield from _scene({**sequence, **condition}, order, {"timestamp": 1})
        times.append(found and found["timestamp"])
    first, last, previous, after = times
    log = scene.get("log", [])
    return Frame(scene_id=scene["_id"], robot=robot, map=scene["map"], time=t,
                 clusters=scene.get("summary", {}).get("clusters", 0),
                 failed=sorted({line.get("source") or "" for line in log
                                if line.get("level") == "error"}),
                 first=first, last=last, previous=previous, next=after)
