"""The review queue: the clusters of the latest scenes a person should look at first, ranked by
how unsure the memory is about them (issue 21), so that each correction fixes the most.

Two kinds of doubt, each in [0, 1]; a cluster ranks by the larger:
- annotators disagree: of the names its annotations give it (naming.py: weighted by type,
  confidence, agreement), the share the heaviest name lacks (one name: 0; "cup" 0.9 against
  "mug" 0.8: 0.47);
- identity had a close alternative: one minus the margin between the probability of the
  decision taken (consolidation.py's events) and that of the best alternative it considered.
Clusters a person corrected already leave the queue; they are counted as fixed. Like the
annotators page, the queue looks at the latest `window` scenes (the scenes' `newest` index,
the clusters' `scene` index, the events' `scene` index): its cost does not grow with the
memory, and what is new comes first.
"""

from __future__ import annotations

from dataclasses import dataclass

from bson import ObjectId
from pymongo import DESCENDING

from percept_memory.converters import registered_types
from percept_memory.memory import documents as docs
from percept_memory.memory.naming import naming_labels
from percept_memory.memory.schema import CLUSTERS, EVENTS, OBJECTS, SCENES
from percept_memory.memory.store import MemoryStore
from percept_memory.memory.types import Annotation
from percept_memory.memory.types.curation import Correction, in_force

DEFAULT_WINDOW, MAX_WINDOW = 500, 5000
DEFAULT_SHOWN, MAX_SHOWN = 50, 500
NAMES_SHOWN = 3


@dataclass
class Doubt:
    """A cluster worth a person's look: why, and how much (`score`, in [0, 1])."""

    cluster_id: ObjectId
    scene_id: ObjectId
    time: int
    region: str | None
    object_id: ObjectId | None
    object_name: str | None
    names: list[tuple[str, float]]  # what the annotations name it, heaviest first
    disagreement: float
    decision: dict | None  # {explanation, probability, alternative: {explanation, probability,
    # object_id}} when identity considered an alternative
    closeness: float

    @property
    def score(self) -> float:
        return max(self.disagreement, self.closeness)


@dataclass
class Queue:
    scenes: int  # in the window
    clusters: int  # in the window
    fixed: int  # of those, corrected by a person
    doubts: list[Doubt]  # the most doubtful first


def naming_types() -> list[str]:
    """The annotation types that name an object (what disagreement is about), corrections
    included (so that a corrected cluster is known), none of the bulky descriptor types."""
    return sorted(name for name, kind in registered_types().items()
                  if issubclass(kind, Annotation)
                  and (kind.naming_weight > 0 or issubclass(kind, Correction)))


def review_queue(store: MemoryStore, window: int = DEFAULT_WINDOW, shown: int = DEFAULT_SHOWN,
                 robot: str | None = None) -> Queue:
    """The doubtful clusters of the latest `window` scenes (of `robot`), most doubtful first."""
    scenes = list(store.db[SCENES].find({"robot": robot} if robot else {}, {"_id": 1})
                  .sort([("timestamp", DESCENDING), ("_id", DESCENDING)]).limit(window))
    scene_ids = [s["_id"] for s in scenes]
    kinds = naming_types()
    found = store.db[CLUSTERS].find({"scene_id": {"$in": scene_ids}}, {
        "scene_id": 1, "object_id": 1, "time": "$search.time", "region": "$search.region",
        "annotations": {"$filter": {"input": {"$ifNull": ["$annotations", []]},
                                    "cond": {"$in": ["$$this._type", kinds]}}}})
    decisions = _closest_calls(store, scene_ids)
    doubts, clusters, fixed = [], 0, 0
    for doc in found:
        clusters += 1
        said = docs.decode_cluster({"_id": doc["_id"], "_type": "pm.scene.Cluster",
                                    "annotations": doc["annotations"]}, {}).annotations
        if any(isinstance(a, Correction) for a in in_force(said)):
            fixed += 1
            continue
        names = naming_labels(said).most_common()
        total = sum(weight for _, weight in names)
        disagreement = 1 - names[0][1] / total if total > 0 else 0.0
        decision = decisions.get(doc["_id"])
        closeness = decision["closeness"] if decision else 0.0
        if disagreement > 0 or closeness > 0:
            doubts.append(Doubt(doc["_id"], doc["scene_id"], doc.get("time"), doc.get("region"),
                                doc.get("object_id"), None, names[:NAMES_SHOWN],
                                round(disagreement, 3), decision, round(closeness, 3)))
    doubts.sort(key=lambda d: (-d.score, -(d.time or 0), d.cluster_id))
    doubts = doubts[:shown]
    _name_objects(store, doubts)
    return Queue(len(scenes), clusters, fixed, doubts)


def _closest_calls(store: MemoryStore, scene_ids: list) -> dict[ObjectId, dict]:
    """Per cluster of these scenes whose identity decision had an alternative: the decision,
    its best alternative and how close they came (1: a coin toss)."""
    out = {}
    for event in store.db[EVENTS].find(
            {"scene_id": {"$in": scene_ids}, "alternatives.1": {"$exists": True}},
            {"cluster_id": 1, "object_id": 1, "explanation": 1, "probability": 1,
             "alternatives": 1}):
        others = [a for a in event["alternatives"] if not _taken(a, event)]
        if event.get("cluster_id") is None or not others:
            continue
        best = max(others, key=lambda a: a.get("probability", 0.0))
        margin = event["probability"] - best.get("probability", 0.0)
        out[event["cluster_id"]] = {
            "explanation": event["explanation"], "probability": event["probability"],
            "alternative": best, "closeness": min(max(1.0 - margin, 0.0), 1.0)}
    return out


def _taken(alternative: dict, event: dict) -> bool:
    """Whether the alternative is the decision itself (identity lists every option it
    weighed, the one it took among them; a new object's has no id yet)."""
    return alternative.get("explanation") == event["explanation"] and alternative.get(
        "object_id") in (event["object_id"], None)


def _name_objects(store: MemoryStore, doubts: list[Doubt]) -> None:
    ids = {d.object_id for d in doubts if d.object_id} | {
        d.decision["alternative"].get("object_id") for d in doubts if d.decision}
    names = {o["_id"]: o.get("name") for o in store.db[OBJECTS].find(
        {"_id": {"$in": [i for i in ids if i is not None]}}, {"name": 1})}
    for doubt in doubts:
        doubt.object_name = names.get(doubt.object_id)
        if doubt.decision:
            alternative = doubt.decision["alternative"]
            alternative["object_name"] = names.get(alternative.get("object_id"))

