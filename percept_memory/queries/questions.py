"""Questions about objects, answered from the belief state: `objects` (what is believed to
exist, where, in which state) and `events` (per object per scene: appear, stay, move,
newview, hidden, disappear, with the position and region). Both are written by
memory/consolidation.py; only the document shapes its docstring gives are relied on here.

The thesis (8.3) answers "where is X" by the most recent matching observation and "where was
X" by walking tracking annotations back; the belief state lets us answer what the robot
believes, including objects it cannot see now (hidden), for any moment in the past: the
belief about an object at time t is its last event at or before t.
"""

from __future__ import annotations

from bson import ObjectId
from bson.min_key import MinKey

from percept_memory.converters import name_of, unescape_key
from percept_memory.memory.errors import NotFound
from percept_memory.memory.schema import CLUSTERS, EVENTS, LABELS, MAPS, OBJECTS
from percept_memory.memory.search_keys import words
from percept_memory.memory.types import Rejection

from .compile import time_window
from .model import About, AtTime, Between, History, Place
from .ops import Aggregate, Find, Plan, QueryError
from .results import (
    NOW,
    Belief,
    Changes,
    Contents,
    Moved,
    ObjectAt,
    Sighting,
    Stay,
    position_sigma,
)
from .results import History as HistoryAnswer
from .space import Coordinates, inside
from .text import all_terms, expand, word_score

EVENT_PLACE = Coordinates.array("position")
STATE_OF = {"appear": "present", "stay": "present", "move": "present", "newview": "present",
            "hidden": "hidden", "disappear": "disappeared"}
STATE_ORDER = {"present": 0, "hidden": 1, "disappeared": 2}
MAX_LABELS = 500  # labels a text may stand for
MAX_CANDIDATES = 500  # objects those labels may name
EVIDENCE = 3  # most recent observations given with a belief
OBJECT_FIELDS = {"label_weights": 0}
FULL_NAME_SHARE = 0.25  # of the top name's weight: a name that heavy names the object fully


# --- which objects a question is about -------------------------------------------------------


def resolve(x: str, limit: int, map_name: str | None = None
            ) -> Plan[list[tuple[dict, float]]]:
    """The objects X stands for (in one map, if given), best first, with how well they
    match: an object id, a cluster id (the object it is believed to be), or text matched
    against the objects' names (misspellings tolerated); ties go to the objects whose name
    the words make up most of, then to present objects before hidden ones before gone ones,
    then to the most recently seen, then to the one seen most often."""
    if ObjectId.is_valid(x):
        found = yield from _by_id(ObjectId(x))
        if map_name is not None and found.get("map") != map_name:
            raise NotFound("object", f"{x} in map {map_name!r}", f"it is in {found.get('map')!r}")
        return [(found, 1.0)]
    query_words = tuple(dict.fromkeys(words(x)))
    if not query_words:
        raise QueryError(f"{x!r} names nothing: give words, an object id or a cluster id")
    expansions = yield from expand(query_words)
    terms = all_terms(expansions)
    labels = yield Find(LABELS, {"words": {"$in": terms}}, {"_id": 1}, limit=MAX_LABELS)
    names = sorted({*terms, *(doc["_id"] for doc in labels)})  # a one-word name is its word
    in_map = {} if map_name is None else {"map": map_name}
    objects = yield Find(OBJECTS, {"names": {"$in": names}, **in_map}, limit=MAX_CANDIDATES)
    scored = [(o, word_score(expansions, name_words(o)) / len(query_words)) for o in objects]
    scored.sort(key=lambda s: (-s[1], -named_by(s[0], set(terms)),
                               STATE_ORDER.get(s[0].get("state"), 3),
                               -(s[0].get("last_seen") or 0), -s[0].get("observations", 0)))
    return scored[:limit]


def named_by(o: dict, terms: set[str]) -> float:
    """How much of one of the object's names the words asked make up: "cup" is all of the
    name of a cup, a third of "cup eco orange" (a tie-break after the match: the exact name
    first; an object called heinz and ketchup is all "ketchup" too)."""
    return max((sum(word in terms for word in name) / len(name)
                for name in map(words, o.get("names") or []) if name), default=0.0)


def name_words(o: dict) -> dict[str, float]:
    """The words of an object's names, each weighted by how much its name names the object
    (thesis 5.4.5, word statistics), so "mug" finds the object called mug before the cup once
    taken for a mug. A name FULL_NAME_SHARE as heavy as the top one names it fully: two
    ketchups both called "heinz" and "ketchup" match "ketchup" equally, whatever the shares,
    and their state decides which comes first; a lighter name counts for its share of that."""
    weights = {unescape_key(k): v for k, v in (o.get("label_weights") or {}).items()}
    top = max(weights.values(), default=0)
    have: dict[str, float] = {}
    for name in o.get("names") or []:
        weight = min(1.0, weights.get(name, 0) / top / FULL_NAME_SHARE) if top > 0 else 1.0
        for word in words(name):
            have[word] = max(have.get(word, 0.0), weight)
    return have


REJECTION = name_of(Rejection)
REJECTED = "a person rejected it (a detection of nothing: `pmem corrections` lists it)"


def _by_id(given: ObjectId) -> Plan[dict]:
    """The object of this id, or of the cluster of this id (a cluster of no object says
    why)."""
    found = yield Find(OBJECTS, {"_id": given}, OBJECT_FIELDS)
    if found:
        return found[0]
    cluster = yield Find(CLUSTERS, {"_id": given}, {"object_id": 1, "annotations._type": 1,
                                                    "search.map": 1})
    if not cluster:
        raise NotFound("object or cluster", given)
    if cluster[0].get("object_id") is None:
        said = {a.get("_type") for a in cluster[0].get("annotations", [])}
        raise NotFound("object of the cluster", given, REJECTED if REJECTION in said else
                       "its scene is not consolidated yet (`pmem pipeline` says how far)")
    found = yield Find(OBJECTS, {"_id": cluster[0]["object_id"]}, OBJECT_FIELDS)
    if not found:  # (its object is gone from the belief, which is being made again)
        map_name = cluster[0].get("search", {}).get("map")
        raise NotFound("object of the cluster", given, "it is not in the belief now"
                       + (f": the belief of map {map_name} is being rebuilt (`pmem pipeline` "
                          "says how far)" if map_name else ""))
    return found[0]


# --- where is, last seen, where was ----------------------------------------------------------


def where_is(q: About) -> Plan[list[Belief]]:
    """What the memory believes about the objects X names now: state (present, hidden,
    disappeared), position, region, last seen, the confidence of its last explanation and
    the observations that are the evidence."""
    return (yield from beliefs((yield from resolve(q.x, q.limit, q.map))))


def beliefs(found: list[tuple[dict, float]]) -> Plan[list[Belief]]:
    """The objects found, each with the confidence of its last explanation and its latest
    observations (the evidence)."""
    last = yield from latest_events({"$in": [o["_id"] for o, _ in found]}, NOW)
    confidence = {e["object_id"]: e.get("probability") for e in last}
    out = []
    for o, match in found:
        evidence = yield Find(CLUSTERS, {"object_id": o["_id"]}, {"_id": 1},
                              (("search.time", -1), ("_id", -1)), EVIDENCE)
        out.append(_belief(o, match, confidence.get(o["_id"]), [c["_id"] for c in evidence]))
    return out


def last_seen(q: About) -> Plan[list[Sighting]]:
    """When and where the objects X names were last observed, most recent first."""
    found = yield from resolve(q.x, q.limit, q.map)
    sightings = [Sighting(object_id=o["_id"], name=o.get("name"), time=o["last_seen"],
                          region=o.get("region"), position=o.get("position"),
                          cluster_id=o.get("last_cluster"), scene_id=o.get("last_scene"),
                          robot=o.get("robot"), state=o["state"], match=match)
                 for o, match in found]
    return sorted(sightings, key=lambda s: (-s.match, -s.time))


def where_was(q: History) -> Plan[list[HistoryAnswer]]:
    """The places each object X names was at, with the times, oldest first; within a time
    window, those it was at during it, each whole (its stay begun before the window keeps its
    start and its sightings)."""
    found = yield from resolve(q.x, q.limit, q.map)
    ids = [o["_id"] for o, _ in found]
    upto = {"time": time_window(None, q.before)} if q.before is not None else {}
    events = yield Find(EVENTS, {"object_id": {"$in": ids}, **upto}, STAY_FIELDS,
                        (("object_id", 1), ("time", -1)))
    if q.before is not None:  # the stay open at `before` read on to its end: whole
        events += yield from _to_the_end_of_stays(ids, q.before)
    by_object: dict = {}
    for event in sorted(events, key=lambda e: e["time"]):  # oldest first
        by_object.setdefault(event["object_id"], []).append(event)
    answers = []
    for (o, _), belief in zip(found, (yield from beliefs(found)), strict=True):
        places = [stay for stay in stays(by_object.get(o["_id"], []))
                  if (q.after is None or stay.until is None or stay.until >= q.after)
                  and (q.before is None or stay.since <= q.before)]
        if places and places[-1].until is None and o.get("position") is not None:
            places[-1].position = tuple(o["position"])  # where it is now: its own estimate
        answers.append(HistoryAnswer(object=belief, places=places[-MAX_PLACES:],
                                     earlier_places=max(len(places) - MAX_PLACES, 0)))
    return answers


STAY_FIELDS = {"object_id": 1, "time": 1, "explanation": 1, "region": 1, "position": 1}
ENDS_A_STAY = ["appear", "move", "disappear"]
STARTS_A_STAY = ["appear", "move"]
SIGHTINGS = ("appear", "move", "stay", "newview")  # the events of an observation
MAX_PLACES = 200  # an object's places in a where-was answer, the latest (README)


def _to_the_end_of_stays(ids: list, before: int) -> Plan[list[dict]]:
    """Each object's events after `before` up to the one that ends the stay it was in then
    (a move or a disappear; none: up to now), one index seek each to find that end."""
    spans = []
    for object_id in ids:
        end = yield Find(EVENTS, {"object_id": object_id, "time": {"$gt": before},
                                  "explanation": {"$in": ENDS_A_STAY}}, {"time": 1},
                         (("object_id", 1), ("time", 1)), 1)
        spans.append({"object_id": object_id,
                      "time": {"$gt": before, **({"$lte": end[0]["time"]} if end else {})}})
    if not spans:
        return []
    return (yield Find(EVENTS, {"$or": spans}, STAY_FIELDS))


def stays(events: list[dict]) -> list[Stay]:
    """Events of one object, oldest first, as the places it was at: an appear or a move
    starts a stay, stay and newview extend it, hidden marks it unseen (still believed
    there), disappear or the next move ends it. A place's position is the mean of where it
    was seen there (each sighting is one noisy observation; unseen there, where it was
    believed)."""
    out: list[Stay] = []
    seen_at: list[list] = []  # per stay, the positions of its sightings
    for e in events:
        kind, t = e["explanation"], e["time"]
        current = out[-1] if out and out[-1].until is None else None
        if kind in ("appear", "move") or current is None:
            if current is not None:
                current.until, current.ended_by = t, "move"
            if kind == "disappear":
                continue
            current = Stay(region=e.get("region"), position=e.get("position"), since=t,
                           last_seen=t, observations=int(kind != "hidden"),
                           hidden_since=t if kind == "hidden" else None)
            out.append(current)
            seen_at.append([])
        elif kind in ("stay", "newview"):
            current.last_seen, current.hidden_since = t, None
            current.observations += 1
        elif kind == "hidden":
            current.hidden_since = t
        elif kind == "disappear":
            current.until, current.ended_by = t, "disappear"
        if kind in SIGHTINGS and e.get("position") is not None:
            seen_at[-1].append(e["position"])
    for stay, positions in zip(out, seen_at, strict=True):
        if positions:
            stay.position = tuple(sum(axis) / len(positions)
                                  for axis in zip(*positions, strict=True))
    return out


def _belief(o: dict, match: float, confidence: float | None = None,
            evidence: list | None = None) -> Belief:
    stored = {key: o[key] for key in Belief.model_fields if o.get(key) is not None}
    return Belief(**{**stored, "object_id": o["_id"], "position_sigma": position_sigma(o),
                     "confidence": confidence,
                     "evidence": evidence or [], "match": round(match, 3)})


# --- what is at a place, what changed there --------------------------------------------------


def latest_events(objects: dict, t: int, place: Place | None = None,
                  fields: dict | None = None) -> Plan[list[dict]]:
    """The belief about each object at time t (its last event at or before t), of the
    objects whose ids meet the condition; with a place, only the objects believed there then
    (present or hidden); with fields, only those of each event (a projection). One index seek
    per object (DISTINCT_SCAN on events' object_time index)."""
    pipeline: list[dict] = [
        {"$match": {"object_id": objects, "time": {"$lte": t}}},
        {"$sort": {"object_id": 1, "time": -1}},
        {"$group": {"_id": "$object_id", "event": {"$first": "$$ROOT"}}},
        {"$replaceWith": "$event"},
    ]
    if place is not None:
        pipeline.append({"$match": {**_at(place), "explanation": {"$ne": "disappear"}}})
    if fields is not None:
        pipeline.append({"$project": fields})
    return (yield Aggregate(EVENTS, pipeline))


def ever_at(place: Place, t: int) -> Plan[dict]:
    """A condition on object ids that every object believed at the place at t meets: for a
    region, an event there by t (one index seek per object ever there, however many objects
    the memory knows elsewhere); for a map, its objects; for a volume, any object."""
    in_map = {} if place.map is None else {"map": place.map}
    if place.region is None:
        if place.map is None:
            return {"$gte": MinKey()}
        found = yield Find(OBJECTS, in_map, {"_id": 1})
        if not found and not (yield Find(MAPS, {"_id": place.map}, {"_id": 1}, limit=1)):
            raise NotFound("map", repr(place.map), "maps: " + (yield from _known(MAPS, "_id")))
        return {"$in": [doc["_id"] for doc in found]}
    found = yield Aggregate(EVENTS, [
        {"$match": {"region": place.region, "time": {"$lte": t}, **in_map}},
        {"$sort": {"region": 1, "object_id": 1}},
        {"$group": {"_id": "$object_id"}},
    ])
    if not found and not (yield Find(EVENTS, {"region": place.region, **in_map}, {"_id": 1},
                                     limit=1)):  # a name no object was ever seen in
        raise NotFound("region", repr(place.region) + (f" in map {place.map!r}" if place.map
                                                       else ""),
                       "regions: " + (yield from _known(OBJECTS, "region", in_map)))
    return {"$in": [doc["_id"] for doc in found]}


def _known(collection: str, field: str, condition: dict | None = None) -> Plan[str]:
    """The names a misspelt one may have meant (matched exactly: a region's name is its
    annotators' own)."""
    found = yield Aggregate(collection, [{"$match": condition or {}},
                                         {"$group": {"_id": f"${field}"}}, {"$sort": {"_id": 1}}])
    return ", ".join(repr(doc["_id"]) for doc in found if doc["_id"] is not None) or "none yet"


def _at(place: Place) -> dict:
    if place.region is not None:
        return {"region": place.region}
    if place.box or place.sphere:
        return inside(place.box or place.sphere, EVENT_PLACE)
    return {}


def what_is_at(q: AtTime) -> Plan[Contents]:
    """The objects believed at the place at time t (default now), present or hidden."""
    t = NOW if q.t is None else q.t
    believed = yield from latest_events((yield from ever_at(q, t)), t, q)
    ids = [e["object_id"] for e in believed]
    found = yield Find(OBJECTS, {"_id": {"$in": ids}}, {"name": 1, "position": 1})
    names = {o["_id"]: o.get("name") for o in found}
    began = yield from stays_began(ids, t)
    if q.t is None:  # now: each where the belief puts it now, from all its sightings there
        estimated = {o["_id"]: o["position"] for o in found if o.get("position") is not None}
        believed = [{**e, "position": estimated.get(e["object_id"], e.get("position"))}
                    for e in believed]  # (as where-is)
    return Contents(t=t, objects=_objects_at(believed, names, began))


def changes(q: Between) -> Plan[Changes]:
    """What changed at the place between t1 and t2 (default now): objects that appeared
    there, that disappeared from there (and where they went), that moved within it. Net
    changes: an object that came and went in between is not listed."""
    t2 = NOW if q.t2 is None else q.t2
    candidates = yield from ever_at(q, t2)  # (those of t1 among them)
    before = {e["object_id"]: e for e in (yield from latest_events(candidates, q.t1, q))}
    after = {e["object_id"]: e for e in (yield from latest_events(candidates, t2, q))}
    gone = [o for o in before if o not in after]
    went = {e["object_id"]: e for e in (yield from latest_events({"$in": gone}, t2))}
    stayed = [o for o in before if o in after]
    moves = yield Find(EVENTS, {"object_id": {"$in": stayed}, "time": {"$gt": q.t1, "$lte": t2},
                                "explanation": "move"}, {"object_id": 1})
    moved = {e["object_id"] for e in moves}
    names = yield from names_of([*before, *after])
    began_before = yield from stays_began(list(before), q.t1)
    began = yield from stays_began(list(after), t2)
    appeared = _objects_at([e for o, e in after.items() if o not in before], names, began)

    def pair(o) -> Moved:
        was, now = before[o], after.get(o, went.get(o))
        return Moved(object_id=o, name=names.get(o), before=object_at(was, names, began_before),
                     after=object_at(now, names, began) if now else None)

    return Changes(t1=q.t1, t2=t2, appeared=appeared, disappeared=[pair(o) for o in gone],
                   moved=[pair(o) for o in stayed if o in moved])


def names_of(ids: list) -> Plan[dict]:
    found = yield Find(OBJECTS, {"_id": {"$in": ids}}, {"name": 1})
    return {o["_id"]: o.get("name") for o in found}


def _objects_at(events: list[dict], names: dict, began: dict) -> list[ObjectAt]:
    return sorted((object_at(e, names, began) for e in events),
                  key=lambda o: (o.region or "", o.name or "", str(o.object_id)))


def stays_began(object_ids: list, t: int) -> Plan[dict]:
    """When each object came to where it is believed at t: its last appear or move by then."""
    found = yield Aggregate(EVENTS, [
        {"$match": {"object_id": {"$in": object_ids}, "time": {"$lte": t},
                    "explanation": {"$in": STARTS_A_STAY}}},
        {"$sort": {"object_id": 1, "time": -1}},
        {"$group": {"_id": "$object_id", "time": {"$first": "$time"}}}])
    return {doc["_id"]: doc["time"] for doc in found}


def object_at(e: dict, names: dict, began: dict | None = None) -> ObjectAt:
    """The object as event e leaves it; there `since` its stay began (`began`: stays_began),
    or gone since e itself."""
    since = e["time"] if e["explanation"] == "disappear" else (began or {}).get(
        e["object_id"], e["time"])
    return ObjectAt(object_id=e["object_id"], map=e.get("map"), name=names.get(e["object_id"]),
                    state=STATE_OF[e["explanation"]], region=e.get("region"),
                    position=e.get("position"), since=since, explanation=e["explanation"],
                    cluster_id=e.get("cluster_id"))
