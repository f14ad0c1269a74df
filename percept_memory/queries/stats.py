"""Statistics: annotation histograms per type and per annotator (thesis tables 8.5 and 8.7),
where objects usually are (object-location co-occurrence, thesis 6.6: "where they usually
stand"), also by hour of the day, and per-annotator timings from the scenes' logs.

Each reads the documents its filter selects (by index); without a filter, that is the whole
memory, within the query time limit.
"""

from __future__ import annotations

from collections import Counter

from percept_memory.memory.schema import CLUSTERS, EVENTS, SCENES

from .clusters import compiled
from .compile import time_window
from .model import ClusterFilter, Cooccurrence, Timings
from .ops import Aggregate, Count, Plan
from .questions import names_of, resolve
from .results import AnnotationStats, CooccurrenceStats, Occurrence, Timing, TimingStats
from .results import Count as CountRow

HOUR_NS = 3_600_000_000_000
MAX_OBJECTS = 50


def annotations(f: ClusterFilter) -> Plan[AnnotationStats]:
    """How many annotations of each type, and of each type by each annotator (`source`), the
    selected clusters carry."""
    match, _ = yield from compiled(f)
    rows = yield Aggregate(CLUSTERS, [
        {"$match": match},
        {"$project": {"annotations._type": 1, "annotations.source": 1}},
        {"$unwind": "$annotations"},
        {"$group": {"_id": {"type": "$annotations._type", "annotator": "$annotations.source"},
                    "count": {"$sum": 1}}},
    ])
    clusters = yield Count(CLUSTERS, match)
    by_type: Counter = Counter()
    for row in rows:
        by_type[row["_id"]["type"]] += row["count"]
    by_annotator = [CountRow(type=r["_id"]["type"], annotator=r["_id"].get("annotator") or "",
                             count=r["count"]) for r in rows]
    return AnnotationStats(
        clusters=clusters,
        by_type=[CountRow(type=t, count=n) for t, n in sorted(by_type.items(),
                                                               key=lambda i: (-i[1], i[0]))],
        by_annotator=sorted(by_annotator, key=lambda c: (c.type, -c.count, c.annotator)))


def cooccurrence(q: Cooccurrence) -> Plan[CooccurrenceStats]:
    """How often each object was observed in each region (and at which hour of the day, UTC):
    of the objects X names (those matching it best), or of every object."""
    match: dict = {"cluster_id": {"$ne": None}}
    if q.x is not None:
        found = yield from resolve(q.x, MAX_OBJECTS)
        best = max((score for _, score in found), default=0)
        match["object_id"] = {"$in": [o["_id"] for o, score in found if score == best]}
    if window := time_window(q.after, q.before):
        match["time"] = window
    key: dict = {"object": "$object_id", "region": "$region"}
    if q.by_hour:
        key["hour"] = {"$toInt": {"$mod": [{"$floor": {"$divide": ["$time", HOUR_NS]}}, 24]}}
    rows = yield Aggregate(EVENTS, [{"$match": match},
                                    {"$group": {"_id": key, "count": {"$sum": 1}}}])
    names = yield from names_of(sorted({r["_id"]["object"] for r in rows}))
    per_object = [Occurrence(object_id=r["_id"]["object"], name=names.get(r["_id"]["object"]),
                             region=r["_id"].get("region"), hour=r["_id"].get("hour"),
                             count=r["count"]) for r in rows]
    totals: Counter = Counter()
    for row in per_object:
        totals[row.region, row.hour] += row.count
    return CooccurrenceStats(
        rows=sorted(per_object, key=lambda r: (-r.count, r.name or "", r.region or "",
                                               -1 if r.hour is None else r.hour,
                                               str(r.object_id))),  # (ties: the same order)
        regions=[Occurrence(region=region, hour=hour, count=n)
                 for (region, hour), n in sorted(totals.items(),
                                                 key=lambda i: (-i[1], str(i[0])))])


def timings(q: Timings) -> Plan[TimingStats]:
    """Per annotator, from the scenes' log lines: runs, mean, longest and total duration,
    warnings and errors."""
    match: dict = {}
    if q.robot is not None:
        match["robot"] = q.robot
    if window := time_window(q.after, q.before):
        match["timestamp"] = window
    rows = yield Aggregate(SCENES, [
        {"$match": match},
        {"$project": {"log.source": 1, "log.duration_ms": 1, "log.level": 1}},
        {"$unwind": "$log"},
        {"$group": {"_id": "$log.source",
                    "runs": {"$sum": {"$cond": [{"$isNumber": "$log.duration_ms"}, 1, 0]}},
                    "mean": {"$avg": "$log.duration_ms"}, "max": {"$max": "$log.duration_ms"},
                    "total": {"$sum": "$log.duration_ms"},
                    "warnings": {"$sum": {"$cond": [{"$eq": ["$log.level", "warning"]}, 1, 0]}},
                    "errors": {"$sum": {"$cond": [{"$eq": ["$log.level", "error"]}, 1, 0]}}}},
        {"$sort": {"_id": 1}},
    ])
    scenes = yield Count(SCENES, match)
    return TimingStats(scenes=scenes, annotators=[
        Timing(annotator=r["_id"] or "", runs=r["runs"], mean_ms=r["mean"], max_ms=r["max"],
               total_ms=r["total"], warnings=r["warnings"], errors=r["errors"]) for r in rows])
