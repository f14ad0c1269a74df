"""The annotators page, for whoever debugs an annotator (DESIGN.md, user 3): over the latest
scenes (a window the URL sets), per annotator how many annotations it made, how often it ran,
its mean, 95th percentile and longest time, its warnings and errors, the latest error lines
themselves, and the clusters on which annotators disagree: classifications from different
sources with different classes.

Times come from the scenes' log lines (`duration_ms`). The 95th percentile needs every
duration, which MongoDB 6.0 cannot rank in an aggregation ($percentile came with 7.0), so the
window's log lines are read once and summed up here; the window keeps that read bounded.
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass, field

import numpy as np
from fastapi import APIRouter, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import HTMLResponse
from pymongo import DESCENDING

from percept_memory.converters import name_of
from percept_memory.memory.schema import CLUSTERS
from percept_memory.memory.store import MemoryStore
from percept_memory.memory.types import Classification
from percept_memory.queries.engine import QueryEngine
from percept_memory.queries.model import ClusterFilter

from .html import bounded_int, page

DEFAULT_WINDOW, MAX_WINDOW = 500, 5000
PROBLEMS_SHOWN = 100
DISAGREEMENTS_SHOWN = 100
NO_SOURCE = "(no annotator)"


@dataclass
class AnnotatorRow:
    """One annotator's work over the window."""

    name: str
    annotations: int = 0
    durations: list[float] = field(default_factory=list)
    warnings: int = 0
    errors: int = 0

    @property
    def runs(self) -> int:
        return len(self.durations)

    @property
    def mean_ms(self) -> float | None:
        return float(np.mean(self.durations)) if self.durations else None

    @property
    def p95_ms(self) -> float | None:
        return float(np.percentile(self.durations, 95)) if self.durations else None

    @property
    def max_ms(self) -> float | None:
        return max(self.durations, default=None)


def routes(store: MemoryStore, engine: QueryEngine) -> APIRouter:
    router = APIRouter(include_in_schema=False, default_response_class=HTMLResponse)

    @router.get("/annotators")
    async def annotators_page(request: Request, scenes: str = str(DEFAULT_WINDOW),
                              robot: str = "") -> HTMLResponse:
        window = bounded_int(scenes, "scenes", 1, MAX_WINDOW)
        report = await run_in_threadpool(annotator_report, store, engine, window, robot or None)
        return page(request, "annotators.html", {**report, "window": window, "robot": robot,
                                                 "max_window": MAX_WINDOW})

    return router


def annotator_report(store: MemoryStore, engine: QueryEngine, window: int,
                     robot: str | None) -> dict:
    """Rows per annotator, the latest warning and error lines, and the disagreements, over the
    latest `window` scenes (of `robot`)."""
    found = list(store.scenes.find({"robot": robot} if robot else {},
                                   {"timestamp": 1, "robot": 1, "log": 1})
                 .sort("timestamp", DESCENDING).limit(window))
    rows: dict[str, AnnotatorRow] = {}
    problems = []
    for scene in found:
        for line in scene.get("log") or []:
            name = line.get("source") or NO_SOURCE
            row = rows.setdefault(name, AnnotatorRow(name))
            if isinstance(line.get("duration_ms"), int | float):
                row.durations.append(line["duration_ms"])
            level = line.get("level")
            row.warnings += level == "warning"
            row.errors += level == "error"
            if level in ("warning", "error") and len(problems) < PROBLEMS_SHOWN:
                problems.append({"scene": scene, "annotator": name, **line})
    if found:
        counted = engine.annotation_stats(ClusterFilter(
            after=found[-1]["timestamp"], before=found[0]["timestamp"],
            robot=[robot] if robot else []))
        for count in counted.by_annotator:
            name = count.annotator or NO_SOURCE
            rows.setdefault(name, AnnotatorRow(name)).annotations += count.count
    return {"scenes": len(found), "rows": sorted(rows.values(), key=lambda r: r.name),
            "problems": problems,
            "disagreements": disagreements(store, [s["_id"] for s in found])}


def disagreements(store: MemoryStore, scene_ids: list) -> list[dict]:
    """Clusters of these scenes whose classifications, by different sources, name different
    classes: {cluster_id, scene_id, time, verdicts: {source: [classes]}}, newest first."""
    kind = name_of(Classification)
    found = store.db[CLUSTERS].aggregate([
        {"$match": {"scene_id": {"$in": scene_ids}}},
        {"$project": {"scene_id": 1, "time": "$search.time", "verdicts": {"$map": {
            "input": {"$filter": {"input": {"$ifNull": ["$annotations", []]},
                                  "cond": {"$eq": ["$$this._type", kind]}}},
            "in": {"source": "$$this.source", "class_name": "$$this.class_name"}}}}},
        {"$match": {"verdicts.1": {"$exists": True}}},  # two classifications at least
        {"$sort": {"time": -1}},
    ])
    out = []
    for doc in found:
        verdicts: dict[str, set[str]] = defaultdict(set)
        for verdict in doc["verdicts"]:
            verdicts[verdict.get("source") or NO_SOURCE].add(str(verdict.get("class_name")))
        if len(verdicts) > 1 and len(set().union(*verdicts.values())) > 1:
            out.append({"cluster_id": doc["_id"], "scene_id": doc["scene_id"],
                        "time": doc.get("time"),
                        "verdicts": {s: sorted(c) for s, c in sorted(verdicts.items())}})
            if len(out) == DISAGREEMENTS_SHOWN:
                break
    return out
