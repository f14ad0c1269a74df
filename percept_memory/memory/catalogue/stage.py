"""The catalogue as a stage of the memory pipeline: after identity has linked a scene's
clusters to objects, each observation's views go to its object's current partial model, and a
model that gained views is learnt again (learning.py). A belief stage: rebuilt with its map.

A partial model is an object track's graph of views over at most OBSERVATIONS_PER_MODEL
observations (Duceux 3.4.5: a tracker's sequence of views); then the track starts a new one, so
models stay the size of one look around an object and an object seen for weeks gives the
catalogue several models to cluster, not one that grows for ever. A model is named by the
cluster of its first observation (the same in a rebuild).

Stored: `catalogue` holds one document per partial model {_id, map, object_id, elements,
length, edges [[model, weight]], entry}: `entry` names its cluster (the catalogue entry, an
object learnt); `catalogue_tracks` one per object {_id: object id, map, model, observations,
last (the views of its last observation), seen, last_seen}; `catalogue_history` the entries
that merged or split {map, time, cluster_id (the observation whose learning did it), kind,
before, after}. The learner of each map is kept in
memory, read again when the stored version differs (another consolidator, an aborted
transaction); in it, models are named by their ids' 12 bytes (bytes hash and compare in C,
ObjectIds in Python: most of the learner's time went there).
"""

from __future__ import annotations

from collections.abc import Sequence

from bson import ObjectId
from pymongo import DeleteOne, ReplaceOne

from percept_memory.converters import registered_types

from .. import documents as docs
from ..schema import CATALOGUE, CATALOGUE_HISTORY, CATALOGUE_TRACKS, MAPS
from ..store import MemoryStore
from ..types import Annotation, Hypothesis
from .graph_of_views import GraphOfViews
from .learning import Learner, Parameters
from .views import observation_views

OBSERVATIONS_PER_MODEL = 10
MAX_SINGLETONS = 10_000  # an object seen in one run of observations is a singleton: keep it
# Below this, two models do not belong together. The thesis' 0.01 was for its descriptors; ours
# (the kitchen week of seed 1, models of its true tracks): 95 % of the pairs of models of one
# object score above 0.09, 95 % of the pairs of two objects below 0.015.
LOW_SIMILARITY = 0.03
# A model this much included in another adds nothing to it (the thesis: 0.95). The same
# object's looks vary (a hash's bits, a histogram's bins), so at 0.95 few repeated looks are
# absorbed, and an object seen for a week fills more clusters of 5 models than one: the kitchen
# week of seed 1 had 37 entries for 20 objects at 0.95, 22 at 0.75, none mixing two kinds.
HIGH_INCLUSION = 0.75
VERSION = "catalogue_version"
EVIDENCE = {"object_id": 1, "hypotheses": 1, "annotations": 1, docs.ARRIVED_KEY: 1}
NO_CLOUDS = {"hypotheses.cloud": 0}  # crops and masks are read: their visual words are views


def declared_modalities() -> int:
    """The modalities of the system (max_modalities of eq. 5.7): the types declaring views,
    and the pairs of them an edge can join (a type with itself: a change of view)."""
    n = sum(getattr(kind, "views", None) not in (None, Annotation.views, Hypothesis.views)
            for kind in registered_types().values())
    return n + n * (n + 1) // 2


def home_parameters() -> Parameters:
    return Parameters(max_singletons=MAX_SINGLETONS, max_modalities=declared_modalities(),
                      low_similarity=LOW_SIMILARITY, high_inclusion=HIGH_INCLUSION)


class CatalogueStage:
    """The pipeline stage keeping each map's catalogue current."""

    name = "catalogue"
    belief = True

    def __init__(self, store: MemoryStore, params: Parameters | None = None):
        self.store = store
        self.params = params or home_parameters()
        self.models = store.db[CATALOGUE]
        self.tracks = store.db[CATALOGUE_TRACKS]
        self.history = store.db[CATALOGUE_HISTORY]
        self.maps = store.db[MAPS]
        self._learners: dict[str, tuple[ObjectId | None, Learner]] = {}

    def learner(self, map_name: str, session=None) -> Learner:
        """The map's catalogue as stored now."""
        stored = self.maps.find_one({"_id": map_name}, {VERSION: 1}, session=session) or {}
        version = stored.get(VERSION)
        kept = self._learners.get(map_name)
        if kept is None or version is None or kept[0] != version:
            rows = ((doc["_id"].binary, GraphOfViews(frozenset(doc["elements"])),
                     doc["length"], {other.binary: w for other, w in doc["edges"]})
                    for doc in self.models.find({"map": map_name}, session=session))
            self._learners[map_name] = (version, Learner.restored(self.params, rows))
        return self._learners[map_name][1]

    def apply(self, scene_ids: Sequence[ObjectId], map_name: str, session) -> None:
        learner = self.learner(map_name, session)
        self._learners.pop(map_name)  # until this transaction's writes are known to be in
        scenes = {doc["_id"]: doc for doc in self.store.scenes.find(
            {"_id": {"$in": list(scene_ids)}}, {"clusters": 1, "timestamp": 1},
            session=session)}
        wanted = [c for doc in scenes.values() for c in doc["clusters"]]
        found = list(self.store.clusters.find(
            {"_id": {"$in": wanted}, "object_id": {"$ne": None}}, NO_CLOUDS, session=session))
        blobs = self.store._blobs(found, session)
        clusters = {doc["_id"]: doc for doc in found}
        tracks = {doc["_id"]: doc for doc in self.tracks.find(
            {"_id": {"$in": list({doc["object_id"] for doc in found})}}, session=session)}
        touched, changes = set(), []
        for scene_id in scene_ids:
            scene = scenes.get(scene_id)
            for cluster_id in scene["clusters"] if scene else ():
                doc = clusters.get(cluster_id)
                views = doc and observation_views(docs.decode_cluster(doc, blobs),
                                                  docs.arrived(doc))
                if views:
                    track = tracks.setdefault(doc["object_id"], {
                        "_id": doc["object_id"], "map": map_name, "seen": 0})
                    self._observe(learner, track, cluster_id, views, scene["timestamp"])
                    touched.add(track["_id"])
                    changes += [{"map": map_name, "time": scene["timestamp"],
                                 "cluster_id": cluster_id, "kind": change.kind,
                                 "before": [ObjectId(e) for e in change.before],
                                 "after": [ObjectId(e) for e in change.after]}
                                for change in learner.history]
                    learner.history.clear()
        if touched:
            self.tracks.bulk_write([ReplaceOne({"_id": t}, tracks[t], upsert=True)
                                    for t in sorted(touched)], session=session)
        if changes:
            self.history.insert_many(changes, session=session)
        self._write(learner, map_name, {t["model"].binary: t["_id"] for t in tracks.values()},
                    session)

    def _observe(self, learner: Learner, track: dict, cluster_id: ObjectId, views: list[str],
                 time: int) -> None:
        """Add an observation to the track's model; learn the model again if it grew."""
        if track.get("observations", OBSERVATIONS_PER_MODEL) >= OBSERVATIONS_PER_MODEL:
            track.update(model=cluster_id, elements=[], last=[], observations=0)
        before = set(track["elements"])
        grown = GraphOfViews.of_sequence([track["last"], views] if track["last"] else [views])
        track.update(last=views, observations=track["observations"] + 1,
                     seen=track["seen"] + 1, last_seen=time)
        if not grown.elements <= before:
            track["elements"] = sorted(before | grown.elements)
            learner.learn(track["model"].binary, GraphOfViews(frozenset(track["elements"])),
                          track["observations"])

    def _write(self, learner: Learner, map_name: str, objects: dict, session) -> None:
        """The models that changed, and a new version of the map's catalogue. `objects`: the
        object of each model of this batch's tracks (the others' are read)."""
        writes = []
        elsewhere = [ObjectId(k) for k in learner.changed if k in learner.models
                     and k not in objects]
        if elsewhere:
            stored = self.models.find({"_id": {"$in": elsewhere}}, {"object_id": 1},
                                      session=session)
            objects = {**objects, **{doc["_id"].binary: doc["object_id"] for doc in stored}}
        for key in sorted(learner.changed):
            model_id = ObjectId(key)
            if key not in learner.models:
                writes.append(DeleteOne({"_id": model_id}))
                continue
            model = learner.models[key]
            object_id = objects.get(key)
            writes.append(ReplaceOne({"_id": model_id}, {
                "map": map_name, "object_id": object_id,
                "elements": sorted(model.graph.elements), "length": model.length,
                "edges": [[ObjectId(other), w] for other, w in sorted(learner.edges[key].items())],
                "entry": ObjectId(learner.cluster_of[key])}, upsert=True))
        learner.changed.clear()
        if writes:
            self.models.bulk_write(writes, session=session)
        version = ObjectId()
        self.maps.update_one({"_id": map_name}, {"$set": {VERSION: version}}, session=session)
        self._learners[map_name] = (version, learner)

    def reset(self, map_name: str) -> None:
        """Forget the map's catalogue (it is learnt again from the map's scenes)."""
        self.models.delete_many({"map": map_name})
        self.tracks.delete_many({"map": map_name})
        self.history.delete_many({"map": map_name})
        self.maps.update_one({"_id": map_name}, {"$unset": {VERSION: ""}})
        self._learners.pop(map_name, None)
