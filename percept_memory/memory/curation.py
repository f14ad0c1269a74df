"""Corrections by people: relabel a cluster, reject it, merge two objects, split one, undo any
of them; and the audit of them.

    relabel(store, cluster_id, "mug", author="ana")     # the object seen here is a mug
    reject(store, cluster_id, author="ana")             # no object is here
    merge(store, cluster_id, other_id, author="ana")    # the same object is seen in both
    split(store, object_id, [cluster_id], author="ana") # these observations are another object
    undo(store, cluster_id, correction_id, author="bo") # takes one back (itself recorded)
    audit(store)                                        # every correction, newest first

Each is an annotation appended to the cluster (types/curation.py), beside what annotators said,
in one transaction with what it changes in the belief: the names of the cluster's object follow
at once (store.py renames it, naming.py weighs the correction above everything else). A
correction that changes what identity decides (a rejection: the cluster is no object; a
merge: two objects are one; a split: one object is two; or taking one back) also asks, in the
same transaction, for its map's belief to be rebuilt by the memory pipeline (pipeline.py):
identity then decides the map's scenes again with what people said.
"""

from __future__ import annotations

from collections import Counter
from datetime import UTC, datetime

from bson import ObjectId
from pydantic import TypeAdapter, ValidationError
from pymongo import ASCENDING

from percept_memory.converters import name_of

from .errors import NotFound
from .schema import CLUSTERS, MAPS, OBJECTS, SCENES
from .store import MemoryStore
from .types import Cluster, Rejection, Relabel, Undo, timestamp_from_datetime
from .types.curation import (
    Author,
    Correction,
    DifferentObject,
    SameObject,
    identity_said,
    in_force,
)

AUDIT_LIMIT = 1000
SPLIT_LIMIT = 1000  # observations split off at once
OBSERVATIONS_LIMIT = 100_000  # of an object split: a split names them all (in one document)
KINDS = {name_of(Relabel): "relabel", name_of(Rejection): "reject",
         name_of(SameObject): "merge", name_of(DifferentObject): "split",
         name_of(Undo): "undo"}
UNDOABLE = (Relabel, Rejection, SameObject, DifferentObject)
_author = TypeAdapter(Author)


class NotCorrectable(ValueError):
    """A correction that cannot be made: the message says why (a person can fix it), `field`
    names the field at fault, if one is."""

    def __init__(self, message: str, field: str = ""):
        super().__init__(message)
        self.field = field


def relabel(store: MemoryStore, cluster_id: ObjectId, class_name: str, author: str) -> Relabel:
    """Say what the object seen in the cluster is (a class or a name)."""
    return _append(store, cluster_id, lambda: Relabel(class_name=class_name, **_who(author)))


def reject(store: MemoryStore, cluster_id: ObjectId, author: str, reason: str = "") -> Rejection:
    """Say the cluster's detection is wrong: no object is here."""
    return _append(store, cluster_id, lambda: Rejection(reason=reason, **_who(author)))


def merge(store: MemoryStore, cluster_id: ObjectId, other_id: ObjectId,
          author: str) -> SameObject:
    """Say the two clusters show the same object (their objects are merged). Stored on the
    later of the two, naming the earlier, which identity has decided on by then."""
    if cluster_id == other_id:
        raise NotCorrectable("other: a cluster is the same object as itself already", "other")
    earlier, later = _in_time_order(store, [cluster_id, other_id])
    return _append(store, later, lambda: SameObject(other=earlier, **_who(author)))


def split(store: MemoryStore, object_id: ObjectId, cluster_ids: list[ObjectId],
          author: str) -> DifferentObject:
    """Say these observations of the object show another object than the rest of its
    observations: one correction, stored on the earliest of them, naming both sides. Identity
    then decides the map again and never takes an observation of one side for an object one
    of the other side was taken for: those split off go to another object (together, by
    their likeness, unless a person says more)."""
    cluster_ids = list(dict.fromkeys(cluster_ids))
    if not 0 < len(cluster_ids) <= SPLIT_LIMIT:
        raise NotCorrectable(f"clusters: name 1 to {SPLIT_LIMIT} observations of the object "
                             "to split off", "clusters")
    if store.db[OBJECTS].find_one({"_id": object_id}, {"_id": 1}) is None:
        raise NotFound("object", object_id)
    theirs = [doc["_id"] for doc in store.db[CLUSTERS].find(
        {"object_id": object_id}, {"_id": 1}).sort(
        [("object_id", ASCENDING), ("search.time", ASCENDING)]).limit(OBSERVATIONS_LIMIT + 1)]
    if len(theirs) > OBSERVATIONS_LIMIT:
        raise NotCorrectable(f"object {object_id} has more than {OBSERVATIONS_LIMIT} "
                             "observations: too many to split")
    named, known = set(cluster_ids), set(theirs)
    if stray := [key for key in cluster_ids if key not in known]:
        raise NotCorrectable(f"clusters: {stray[0]} is not an observation of object "
                             f"{object_id}", "clusters")
    if not (rest := [key for key in theirs if key not in named]):
        raise NotCorrectable("clusters: these are all the object's observations: split off "
                             "fewer", "clusters")
    split_off = [key for key in theirs if key in named]  # in time order
    return _append(store, split_off[0], lambda: DifferentObject(
        split_off=split_off, apart_from=rest, **_who(author)))


def _in_time_order(store: MemoryStore, cluster_ids: list[ObjectId]) -> list[ObjectId]:
    """The clusters in the order of their scenes' times (then ids), all of one map: how
    identity meets them."""
    scenes = {doc["_id"]: doc["scene_id"] for doc in store.db[CLUSTERS].find(
        {"_id": {"$in": cluster_ids}}, {"scene_id": 1})}
    for key in cluster_ids:
        if key not in scenes:
            raise NotFound("cluster", key)
    seen = {doc["_id"]: doc for doc in store.db[SCENES].find(
        {"_id": {"$in": list(set(scenes.values()))}}, {"map": 1, "timestamp": 1})}
    if len({seen[scene].get("map") for scene in scenes.values()}) > 1:
        raise NotCorrectable("other: observations in different maps are never one object",
                             "other")
    if len(set(scenes.values())) < len(cluster_ids):
        raise NotCorrectable("other: observations in one scene are of different objects "
                             "(one object is seen once a scene)", "other")
    return sorted(cluster_ids, key=lambda key: (seen[scenes[key]]["timestamp"], key))


def undo(store: MemoryStore, cluster_id: ObjectId, correction_id: ObjectId,
         author: str) -> Undo:
    """Take back a correction of the cluster that is in force."""
    cluster = store.get_cluster(cluster_id)
    if not any(isinstance(a, UNDOABLE) and a.id == correction_id
               for a in in_force(cluster.annotations)):
        raise NotCorrectable(f"cluster {cluster_id} has no correction {correction_id} in force "
                             "to undo")
    return _append(store, cluster_id, lambda: Undo(undoes=correction_id, **_who(author)))


def _who(author: str) -> dict:
    try:
        name = _author.validate_python(author)
    except ValidationError:
        raise NotCorrectable("author: who makes a correction is named (1 to 100 "
                             "characters)", "author") from None
    return {"author": name, "time": timestamp_from_datetime(datetime.now(UTC))}


def _append(store: MemoryStore, cluster_id: ObjectId, make) -> Correction:
    try:
        correction = make()
    except ValidationError as error:
        problem = error.errors(include_url=False, include_input=False)[0]
        field = ".".join(map(str, problem["loc"]))
        raise NotCorrectable(f"{field}: {problem['msg']}", field) from None

    def rebuild_if_identity_changed(before: list, after: Cluster, session) -> None:
        if identity_said(before) != identity_said(after.annotations):
            scene = store.db[SCENES].find_one({"_id": after.scene_id}, {"map": 1},
                                              session=session)
            if scene is not None and scene.get("map"):
                store.db[MAPS].update_one({"_id": scene["map"]}, {"$set": {"rebuild": True}},
                                          upsert=True, session=session)

    store.add_annotations(cluster_id, [correction], then=rebuild_if_identity_changed)
    return correction


def audit(store: MemoryStore, limit: int = AUDIT_LIMIT, author: str | None = None) -> list[dict]:
    """The corrections, newest first (of one author, if given): kind, who, when, what, on
    which cluster, and whether (and by whom) each was undone."""
    match = {"annotations.author": {"$exists": True} if author is None else author}
    rows = list(store.db[CLUSTERS].aggregate([
        {"$match": match},  # the `corrected` index: only corrected clusters are in it
        {"$project": {"scene_id": 1, "object_id": 1, "region": "$search.region",
                      "said": _human_annotations()}},
        {"$unwind": "$said"},
        *([{"$match": {"said.author": author}}] if author is not None else []),
        {"$sort": {"said.time": -1, "said._id": -1}},
        {"$limit": limit},
    ]))
    undone = {u["undoes"]: u for u in _undos(store, {row["_id"] for row in rows})}
    return [_row(row, undone.get(row["said"]["_id"])) for row in rows]


def _human_annotations() -> dict:
    """A cluster's corrections (the annotations with an author, as the index has them)."""
    return {"$filter": {"input": "$annotations",
                        "cond": {"$ne": [{"$type": "$$this.author"}, "missing"]}}}


def _undos(store: MemoryStore, cluster_ids: set) -> list[dict]:
    """The undos on these clusters (a cluster holds few corrections: all are read)."""
    return [a for doc in store.db[CLUSTERS].aggregate([
        {"$match": {"_id": {"$in": list(cluster_ids)}}},
        {"$project": {"said": _human_annotations()}}])
        for a in doc["said"] if a.get("_type") == name_of(Undo)]


def _row(row: dict, undone_by: dict | None) -> dict:
    said = row["said"]
    return {"id": said["_id"], "kind": KINDS.get(said.get("_type"), said.get("_type")),
            "author": said.get("author"), "time": said.get("time"),
            "label": said.get("class_name"), "reason": said.get("reason") or None,
            "other": said.get("other"), **_sides(said, row["_id"]),
            "undoes": said.get("undoes"), "cluster_id": row["_id"],
            "scene_id": row.get("scene_id"), "object_id": row.get("object_id"),
            "region": row.get("region"),
            "undone_by": None if undone_by is None else {
                "id": undone_by["_id"], "author": undone_by.get("author"),
                "time": undone_by.get("time")}}


def _sides(said: dict, cluster_id) -> dict:
    """A split's two sides, as lists. (A split written before splits named both sides kept
    the cluster holding it apart from one other: identity no longer reads it, the audit
    still lists it.)"""
    apart = said.get("apart_from")
    if apart is None or isinstance(apart, list):
        return {"split_off": said.get("split_off"), "apart_from": apart}
    return {"split_off": [cluster_id], "apart_from": [apart]}


def counts(store: MemoryStore) -> dict[str, int]:
    """How many corrections of each kind were made, and on how many clusters."""
    kinds: Counter = Counter()
    clusters = 0
    for doc in store.db[CLUSTERS].aggregate([
            {"$match": {"annotations.author": {"$exists": True}}},
            {"$project": {"said": _human_annotations()}}]):
        clusters += 1
        kinds.update(KINDS.get(a.get("_type"), "other") for a in doc["said"])
    return {**{kind: kinds[kind] for kind in KINDS.values()}, "clusters": clusters}
