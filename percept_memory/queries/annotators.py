"""Annotator reports, for whoever debugs an annotator (DESIGN.md, user 3): over a window of the
latest scenes, per annotator its annotations, times, warnings and errors, in all and hour by
hour, the latest problem lines, and confusion tables of the classes annotators gave (a
classification's class, a detection's name) against each other and against the ground truth
(RoboSherlock's GroundTruth annotations) and the classes people gave in corrections (the
relabel in force), with precision and recall per class.

Times come from the scenes' log lines (`duration_ms`). The database sums the window's lines up
per annotator and hour (newest scenes by index): counts, the scenes warned and failed in, and
the durations, which come back as plain numbers and are ranked here (MongoDB 6.0 cannot rank
in an aggregation: $percentile came with 7.0); the latest problem lines come in a second
command, and the clusters' verdicts are read by the window's scene ids (index `scene`). The
window is a count of scenes, so every read is bounded however large the memory.
"""

from __future__ import annotations

from collections import Counter, defaultdict
from itertools import combinations, product

import numpy as np

from percept_memory.converters import decode, name_of
from percept_memory.memory.schema import CLUSTERS, SCENES
from percept_memory.memory.search_keys import normal_label
from percept_memory.memory.types import Classification, Detection, GroundTruth
from percept_memory.memory.types.curation import Rejection, Relabel, Undo, verdict

from . import stats
from .model import AnnotatorWindow, ClusterFilter, ConfusionCell
from .ops import Aggregate, Find, Plan
from .results import (
    AnnotatorHour,
    AnnotatorReport,
    AnnotatorTotals,
    CellClusters,
    ClassScore,
    Comparison,
    ConfusionCount,
    ProblemLine,
    Verdicts,
)

HOUR_NS = 3_600_000_000_000
PROBLEMS_SHOWN = 100
MAX_COMPARISONS = 20
NO_SOURCE = "(no annotator)"
GROUND_TRUTH = "(ground truth)"
PEOPLE = "(people)"  # the class a person's correction in force gives (memory/types/curation.py)
REFERENCES = (GROUND_TRUTH, PEOPLE)  # what every annotator is compared with, when present
VERDICTS = {name_of(Classification): "class_name", name_of(Detection): "name",
            name_of(GroundTruth): "class_name"}
"""The annotation types that name an object's class, and the field that does."""
CORRECTIONS = [name_of(kind) for kind in (Relabel, Rejection, Undo)]

Cluster = dict[str, set[str]]  # who (annotator or GROUND_TRUTH) -> the classes they gave


def report(w: AnnotatorWindow) -> Plan[AnnotatorReport]:
    """Per annotator, over the latest scenes: annotations, runs, mean / 95th percentile /
    longest time, warnings and errors; the same hour by hour (median and 95th percentile, the
    share of scenes warned or failed in); the latest warning and error lines; and the
    confusion tables of the classes annotators gave, against each other and the ground truth."""
    scenes = yield from _window(w)
    if not scenes:
        return AnnotatorReport(scenes=0, first=None, last=None, annotators=[], hours=[],
                               problems=[], comparisons=[])
    scenes_in_hour = Counter(s["timestamp"] // HOUR_NS * HOUR_NS for s in scenes)
    logged = yield Aggregate(SCENES, [*_latest(w), {"$unwind": "$log"}, {"$group": {
        "_id": {"source": "$log.source", "hour": {"$subtract": [
            "$timestamp", {"$mod": ["$timestamp", HOUR_NS]}]}},
        "times": {"$push": {"$cond": [{"$isNumber": "$log.duration_ms"}, "$log.duration_ms",
                                      "$$REMOVE"]}},
        "warned": {"$addToSet": {"$cond": [{"$eq": ["$log.level", "warning"]}, "$_id",
                                           "$$REMOVE"]}},
        "failed": {"$addToSet": {"$cond": [{"$eq": ["$log.level", "error"]}, "$_id",
                                           "$$REMOVE"]}},
        "warnings": {"$sum": {"$cond": [{"$eq": ["$log.level", "warning"]}, 1, 0]}},
        "errors": {"$sum": {"$cond": [{"$eq": ["$log.level", "error"]}, 1, 0]}}}}])
    hourly: dict[tuple[str, int], dict] = {}
    for row in logged:  # a missing and an empty source are one: no annotator
        key = (row["_id"].get("source") or NO_SOURCE, row["_id"]["hour"])
        if key in hourly:
            row = {k: hourly[key][k] + row[k] for k in ("times", "warned", "failed",
                                                         "warnings", "errors")}
        hourly[key] = row
    totals: dict[str, AnnotatorTotals] = {}
    for (name, _), row in sorted(hourly.items()):
        total = totals.setdefault(name, AnnotatorTotals(annotator=name))
        total.warnings += row["warnings"]
        total.errors += row["errors"]
    for name, total in totals.items():
        # sorted: MongoDB's groups come in any order, and a float sum depends on its order
        values = sorted(t for (who, _), row in hourly.items() if who == name
                        for t in row["times"])
        if values:
            total.runs, total.mean_ms = len(values), float(np.mean(values))
            total.p95_ms, total.max_ms = float(np.percentile(values, 95)), float(max(values))
    counted = yield from stats.annotations(ClusterFilter(
        after=scenes[-1]["timestamp"], before=scenes[0]["timestamp"],
        robot=[w.robot] if w.robot else []))
    for count in counted.by_annotator:
        name = count.annotator or NO_SOURCE
        total = totals.setdefault(name, AnnotatorTotals(annotator=name))
        total.annotations += count.count
    hours = [AnnotatorHour(annotator=name, hour=hour, scenes=scenes_in_hour[hour],
                           runs=len(row["times"]), warned=len(set(row["warned"])),
                           failed=len(set(row["failed"])), **_percentiles(row["times"]))
             for (name, hour), row in sorted(hourly.items())]
    problems = yield Aggregate(SCENES, [
        *_latest(w), {"$unwind": {"path": "$log", "includeArrayIndex": "line"}},
        {"$match": {"log.level": {"$in": ["warning", "error"]}}},
        {"$sort": {"timestamp": -1, "_id": -1, "line": 1}}, {"$limit": PROBLEMS_SHOWN}])
    alike = yield from _verdict_counts([s["_id"] for s in scenes])
    return AnnotatorReport(
        scenes=len(scenes), first=scenes[-1]["timestamp"], last=scenes[0]["timestamp"],
        annotators=sorted(totals.values(), key=lambda t: t.annotator), hours=hours,
        problems=[ProblemLine(scene_id=p["_id"], time=p["timestamp"],
                              annotator=p["log"].get("source") or NO_SOURCE,
                              level=p["log"]["level"], message=str(p["log"].get("message", "")))
                  for p in problems],
        comparisons=comparisons(alike))


def cell(q: ConfusionCell) -> Plan[CellClusters]:
    """The clusters behind one cell of a confusion table of the report on the same window:
    those on which the annotator said `said` and the reference `expected` (left out: said
    nothing), newest first."""
    scenes = yield from _window(q)
    asked = (_normal(q.said), _normal(q.expected))
    found = [(doc, verdicts) for doc, verdicts in (yield from _verdicts([s["_id"] for s in scenes]))
             if asked in _pairs(verdicts, q.annotator, q.reference)]
    return CellClusters(total=len(found), clusters=[
        Verdicts(id=doc["_id"], scene_id=doc["scene_id"], time=doc["time"],
                 verdicts={who: sorted(classes) for who, classes in sorted(verdicts.items())})
        for doc, verdicts in found[:q.limit]])


def comparisons(clusters: list[tuple[Cluster, int]]) -> list[Comparison]:
    """Each annotator against the ground truth and against people's corrections, then each
    pair of annotators, on the clusters either classified, if both classified one at least; in
    that order, those that disagree most first. `clusters`: what was said of clusters, and of
    how many it was."""
    annotators = sorted({who for c, _ in clusters for who in c} - set(REFERENCES))
    references = [r for r in REFERENCES if any(r in c for c, _ in clusters)]
    pairs = [*((a, r) for r in references for a in annotators), *combinations(annotators, 2)]
    compared = [_compared(clusters, annotator, reference) for annotator, reference in pairs
                if any(annotator in c and reference in c for c, _ in clusters)]
    rank = {reference: i for i, reference in enumerate(REFERENCES)}
    compared.sort(key=lambda c: (rank.get(c.reference, len(rank)), -c.disagreements))
    return compared[:MAX_COMPARISONS]


def _compared(clusters: list[tuple[Cluster, int]], annotator: str,
              reference: str) -> Comparison:
    """Classes are compared as the names they make (SiggBottle, sigg_bottle: "sigg bottle")
    and shown as they were most often spelt."""
    cells: Counter = Counter()
    spelt: dict[str, Counter] = defaultdict(Counter)
    said_and_expected: list[tuple[set, set, int]] = []
    compared = disagreeing = 0
    for verdicts, count in clusters:
        pairs = _pairs(verdicts, annotator, reference)
        if not pairs:
            continue
        compared += count
        disagreeing += count * any(said != expected for said, expected in pairs)
        cells.update(dict.fromkeys(pairs, count))
        for name in (*verdicts.get(annotator, ()), *verdicts.get(reference, ())):
            spelt[_normal(name)][name] += count
        said_and_expected.append((*(set(map(_normal, verdicts.get(who, ())))
                                    for who in (annotator, reference)), count))

    def shown(name: str | None) -> str | None:
        return None if name is None else spelt[name].most_common(1)[0][0]
    return Comparison(
        annotator=annotator, reference=reference, clusters=compared, disagreements=disagreeing,
        cells=[ConfusionCount(said=shown(s), expected=shown(e), clusters=n) for (s, e), n in
               sorted(cells.items(), key=lambda i: (str(shown(i[0][1])), str(shown(i[0][0]))))],
        scores=[score.model_copy(update={"class_name": shown(score.class_name)})
                for score in _scores(said_and_expected)])


def _normal(name: str | None) -> str | None:
    return None if name is None else normal_label(name)


def _pairs(verdicts: Cluster, annotator: str, reference: str) -> set[tuple]:
    """The (annotator's class, reference's class) pairs of a cluster, as the names they make,
    None for one that said nothing; none if neither did, nor if people did not correct it:
    people correct a few clusters, so one they left alone is no disagreement with them (the
    ground truth, where there is any, labels every object: a class where it has none is a
    false detection)."""
    said, expected = verdicts.get(annotator), verdicts.get(reference)
    if not expected and (not said or reference == PEOPLE):
        return set()
    return set(product(sorted({normal_label(c) for c in said or ()} or [None]),
                       sorted({normal_label(c) for c in expected or ()} or [None])))


def _scores(clusters: list[tuple[set, set, int]]) -> list[ClassScore]:
    """Precision and recall per class, each cluster counted once per class (an annotator
    that gave a cluster two classes counted it twice in the class's support): a cluster the
    reference did not classify counts in neither; one the annotator did not classify misses
    the reference's class. `clusters`: what the annotator and the reference said of them."""
    classes = sorted({c for said, expected, _ in clusters for c in said | expected})
    scores = []
    for name in classes:
        right = sum(n for said, expected, n in clusters if name in said and name in expected)
        called = sum(n for said, expected, n in clusters if name in said and expected)
        support = sum(n for _, expected, n in clusters if name in expected)
        scores.append(ClassScore(class_name=name, precision=right / called if called else None,
                                 recall=right / support if support else None, support=support))
    return scores


def _percentiles(times: list[float]) -> dict:
    if not times:
        return {}
    p50, p95 = np.percentile(times, [50, 95])
    return {"p50_ms": float(p50), "p95_ms": float(p95)}


def _window(w: AnnotatorWindow) -> Plan[list[dict]]:
    """The window's scenes, newest first: their ids and times (from the index `newest`, or
    `robot_newest`, alone)."""
    match, order = _match(w), (("timestamp", -1), ("_id", -1))
    return (yield Find(SCENES, match, {"timestamp": 1}, sort=order, limit=w.scenes))


def _latest(w: AnnotatorWindow) -> list[dict]:
    """The stages that select the window's scenes with their log lines (the same index): the
    lines are summed up in the database, and only the sums come back."""
    return [{"$match": _match(w)}, {"$sort": {"timestamp": -1, "_id": -1}},
            {"$limit": w.scenes},
            {"$project": {"timestamp": 1, "log.source": 1, "log.level": 1,
                          "log.duration_ms": 1, "log.message": 1}}]


def _match(w: AnnotatorWindow) -> dict:
    match: dict = {}
    if w.robot is not None:
        match["robot"] = w.robot
    if w.before is not None:
        match["timestamp"] = {"$lte": w.before}
    return match


def _verdicts(scene_ids: list) -> Plan[list[tuple[dict, Cluster]]]:
    """The clusters of these scenes that someone classified, newest first, each with who gave
    which classes."""
    found = yield Aggregate(CLUSTERS, [*_said(scene_ids), {"$sort": {"time": -1, "_id": -1}}])
    return [(doc, verdicts) for doc in found if (verdicts := _who_said(doc.pop("verdicts")))]


def _verdict_counts(scene_ids: list) -> Plan[list[tuple[Cluster, int]]]:
    """What was said of the clusters of these scenes, and of how many: clusters said alike
    are counted together in the database (a window's clusters repeat a few verdicts many
    times), a cluster a person corrected on its own (which correction is in force is
    decided here)."""
    corrected = {"$gt": [{"$size": {"$filter": {"input": "$verdicts", "cond": {
        "$in": ["$$this._type", CORRECTIONS]}}}}, 0]}
    found = yield Aggregate(CLUSTERS, [*_said(scene_ids), {"$group": {
        "_id": {"$cond": [corrected, "$_id", "$verdicts"]},
        "verdicts": {"$first": "$verdicts"}, "clusters": {"$sum": 1}}}])
    return [(verdicts, doc["clusters"]) for doc in found
            if (verdicts := _who_said(doc["verdicts"]))]


def _said(scene_ids: list) -> list[dict]:
    """The stages that select the clusters of these scenes someone classified or corrected,
    with what each said (`verdicts`: a class given, or a correction whole)."""
    return [
        {"$match": {"scene_id": {"$in": scene_ids}}},
        {"$project": {"scene_id": 1, "time": "$search.time", "verdicts": {"$map": {
            "input": {"$filter": {"input": {"$ifNull": ["$annotations", []]}, "cond": {
                "$in": ["$$this._type", [*VERDICTS, *CORRECTIONS]]}}},
            "in": {"$cond": [{"$in": ["$$this._type", CORRECTIONS]}, "$$this", {
                "type": "$$this._type", "source": "$$this.source",
                "class": {"$ifNull": ["$$this.class_name", "$$this.name"]}}]}}}}},
        {"$match": {"verdicts.0": {"$exists": True}}},
    ]


def _who_said(said: list[dict]) -> Cluster:
    """Who (an annotator, the ground truth, people) gave which classes, of a cluster's
    verdicts."""
    verdicts: Cluster = defaultdict(set)
    corrections = [decode(v) for v in said if "_type" in v]
    if corrections and isinstance(decided := verdict(corrections), Relabel):
        verdicts[PEOPLE].add(decided.class_name)
    for given in said:
        if "_type" in given or given.get("class") is None:
            continue
        who = GROUND_TRUTH if given.get("type") == name_of(GroundTruth) else (
            given.get("source") or NO_SOURCE)
        verdicts[who].add(str(given["class"]))
    return dict(verdicts)
