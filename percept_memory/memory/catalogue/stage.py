"""The catalogue as a part of the memory pipeline's identity stage: after identity has linked a
scene's clusters to objects, each observation's views go to its object's current partial model,
and a model that gained views is learnt again (learning.py), before the next scene is decided:
identity merges the objects the catalogue learns as one (consolidation.py). Rebuilt with its
map, as the belief is.

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
before, after}. The learner of each map (and the tracks read or written) is kept in
memory, read again when the stored version differs (another consolidator, an aborted
transaction: the version is identity's, written with its calibration in the same
transaction); in it, models are named by their ids' 12 bytes (bytes hash and compare in C,
ObjectIds in Python: most of the learner's time went there).
"""

from __future__ import annotations

from collections.abc import Sequence

from bson import ObjectId
from pymongo import DeleteOne, ReplaceOne, UpdateOne

from ..consolidation import Consolidation
from ..schema import CATALOGUE, CATALOGUE_HISTORY, CATALOGUE_TRACKS
from ..store import MemoryStore
from .graph_of_views import GraphOfViews, inclusion_degree
from .learning import Learner, Parameters
from .views import observation_views

OBSERVATIONS_PER_MODEL = 10
MAX_SINGLETONS = 10_000  # an object seen in one run of observations is a singleton: keep it
# Below this, two models do not belong together. The thesis' 0.01 was for its descriptors;
# ours, weighed over the modalities present (42-43 in the kitchen weeks of seeds 1-3, 2 in the
# identity protocol's worlds 1001-1003): in those kitchens 95 % of the pairs of models of one
# object score above 0.07, 95 % of the pairs of two items below 0.02-0.05; the protocol's
# entries are the same anywhere from 0.03 to 0.15 (its links weigh 0.2-1 or nothing).
LOW_SIMILARITY = 0.06
# A model this much included in another adds nothing to it (the thesis: 0.95). The same
# object's looks vary (a hash's bits, a histogram's bins), so at 0.95 few repeated looks are
# absorbed, and an object seen for a week fills more clusters of 5 models than one: the kitchen
# week of seed 1 had 37 entries for 20 objects at 0.95, 22 at 0.75, none mixing two kinds.
HIGH_INCLUSION = 0.75
# Models an entry keeps (the thesis: 5, for its 6 trajectories per object). A home's object is
# seen for weeks: a new model every OBSERVATIONS_PER_MODEL observations, its looks varying, so a
# full entry of 5 keeps casting one off as an entry of its own. Kitchen weeks of seeds 1-3
# (seed 0 is bench/catalogue.py's): 22, 24, 27 entries for 20 objects at 5; 19, 19, 20 at 8.
MODELS_PER_ENTRY = 8
# The models an object keeps (each of up to OBSERVATIONS_PER_MODEL sightings): one entry's
# worth, so that all of an object's looks can be one entry (_forget_redundant).
MODELS_PER_OBJECT = MODELS_PER_ENTRY
UNREAD = object()  # a version not read yet


def home_parameters() -> Parameters:
    return Parameters(max_singletons=MAX_SINGLETONS, low_similarity=LOW_SIMILARITY,
                      high_inclusion=HIGH_INCLUSION, max_models_per_cluster=MODELS_PER_ENTRY)


class CatalogueStage:
    """Each map's catalogue, kept current as a part of identity's stage of the pipeline
    (consolidation.py: learnt scene by scene, in the same transaction) and read by queries."""

    def __init__(self, store: MemoryStore, params: Parameters | None = None,
                 identity: Consolidation | None = None):
        self.store = store
        self.params = params or home_parameters()
        # the observations' evidence: identity's, which has decoded this batch's already
        self.identity = identity or Consolidation(store)
        self.models = store.db[CATALOGUE]
        self.tracks = store.db[CATALOGUE_TRACKS]
        self.history = store.db[CATALOGUE_HISTORY]
        # map -> (the version its learner is of, the learner, each model's object, the
        # object tracks read or written so far: as stored, by object id)
        self._learners: dict[str, tuple[ObjectId | None, Learner, dict, dict]] = {}

    def learner(self, map_name: str, session=None) -> Learner:
        """The map's catalogue as stored now."""
        return self._learner(map_name, session)[1]

    def _learner(self, map_name: str, session, version=UNREAD
                 ) -> tuple[ObjectId | None, Learner, dict, dict]:
        """The map's learner, read again unless it is of the version stored (identity's)."""
        if version is UNREAD:
            version = self.identity.stored_version(map_name, session)
        kept = self._learners.get(map_name)
        if kept is None or version is None or kept[0] != version:
            docs = list(self.models.find({"map": map_name}, session=session))
            rows = ((doc["_id"].binary, GraphOfViews.of(doc["elements"]),
                     doc["length"], {other.binary: w for other, w in doc["edges"]})
                    for doc in docs)
            self._learners[map_name] = (version, Learner.restored(self.params, rows),
                                        {doc["_id"].binary: doc["object_id"] for doc in docs},
                                        {})
        return self._learners[map_name]

    def begin(self, map_name: str, session, version: ObjectId | None) -> Batch:
        """A batch of scenes of the map to learn, one `observe` per scene in time order, then
        `finish` (the writes, in `session`'s transaction). `version`: identity's, as stored
        when the transaction began."""
        _, learner, objects, tracks = self._learner(map_name, session, version)
        self._learners.pop(map_name)  # until this transaction's writes are known to be in
        return Batch(self, map_name, learner, objects, tracks, session)

    def _write(self, learner: Learner, objects: dict, tracks: dict, map_name: str,
               learnt: dict, session, version: ObjectId) -> None:
        """The models that changed; the learner is kept as of `version`, the one identity
        writes in this transaction. `learnt`: the models learnt (again) in this batch, with
        their objects: written whole; the others only changed their edges or entry (a model's
        elements never change under its id)."""
        writes = []
        for key in sorted(learner.changed):
            model_id = ObjectId(key)
            if key not in learner.models:
                writes.append(DeleteOne({"_id": model_id}))
                continue
            links = {"edges": [[ObjectId(other), w] for other, w in
                               sorted(learner.edges[key].items())],
                     "entry": ObjectId(learner.cluster_of[key])}
            if key in learnt:
                model = learner.models[key]
                writes.append(ReplaceOne({"_id": model_id}, {
                    "map": map_name, "object_id": learnt[key],
                    "elements": sorted(model.graph.elements), "length": model.length, **links},
                    upsert=True))
            else:
                writes.append(UpdateOne({"_id": model_id}, {"$set": links}))
        learner.changed.clear()
        if writes:
            self.models.bulk_write(writes, session=session)
        self._learners[map_name] = (version, learner, objects, tracks)

    def reset(self, map_name: str) -> None:
        """Forget the map's catalogue (it is learnt again from the map's scenes)."""
        self.models.delete_many({"map": map_name})
        self.tracks.delete_many({"map": map_name})
        self.history.delete_many({"map": map_name})
        self._learners.pop(map_name, None)


class Batch:
    """A batch of a map's scenes being learnt (CatalogueStage.begin), scene by scene, and
    which objects the catalogue holds for one (`entry_mates`): as learnt from the scenes so
    far, whatever the batching."""

    def __init__(self, stage: CatalogueStage, map_name: str, learner: Learner, objects: dict,
                 tracks: dict, session):
        self.stage, self.map_name, self.learner, self.session = stage, map_name, learner, session
        self.objects = objects  # model (its id's bytes) -> the object whose track made it
        self.tracks = tracks  # object id -> its track, as read before or grown in this batch
        self.touched, self.learnt, self.changes = set(), {}, []

    def observe(self, cluster_ids: Sequence[ObjectId], time: int) -> list[ObjectId]:
        """Learn one scene's clusters (those identity linked to an object), in order; the
        objects whose model was learnt (again)."""
        objects = self._objects(list(cluster_ids))
        evidence = self.stage.identity.observations(list(objects), self.session)
        learnt: list[ObjectId] = []
        unread = set(objects.values()) - self.tracks.keys() - self.stage.identity.created
        if unread:
            self.tracks.update((doc["_id"], doc) for doc in self.stage.tracks.find(
                {"_id": {"$in": list(unread)}}, session=self.session))
        for cluster_id in cluster_ids:
            views = (cluster_id in objects and cluster_id in evidence
                     and observation_views(evidence[cluster_id].evidence))
            if not views:
                continue
            track = self.tracks.setdefault(objects[cluster_id], {
                "_id": objects[cluster_id], "map": self.map_name, "seen": 0})
            if self._grow(track, cluster_id, views, time):
                self.learnt[track["model"].binary] = track["_id"]
                self.objects[track["model"].binary] = track["_id"]
                learnt.append(track["_id"])
            self.touched.add(track["_id"])
            self.changes += [{"map": self.map_name, "time": time, "cluster_id": cluster_id,
                              "kind": change.kind,
                              "before": [ObjectId(e) for e in change.before],
                              "after": [ObjectId(e) for e in change.after]}
                             for change in self.learner.history]
            self.learner.history.clear()
        return learnt

    def _objects(self, cluster_ids: list) -> dict:
        """The object of each cluster as identity made it by the end of the cluster's scene,
        so that the catalogue learns the same in any batching of the scenes; for clusters
        identity did not decide in this batch (it ran elsewhere), the object they are now."""
        decided = self.stage.identity.decided
        objects = {c: decided[c] for c in cluster_ids if c in decided}
        rest = [c for c in cluster_ids if c not in decided]
        if rest:
            objects.update((doc["_id"], doc["object_id"]) for doc in
                           self.stage.store.clusters.find(
                               {"_id": {"$in": rest}, "object_id": {"$ne": None}},
                               {"object_id": 1}, session=self.session))
        return objects

    def _grow(self, track: dict, cluster_id: ObjectId, views: list[str], time: int) -> bool:
        """Add an observation to the track's model; learn the model again if it grew
        (True)."""
        if track.get("observations", OBSERVATIONS_PER_MODEL) >= OBSERVATIONS_PER_MODEL:
            if "model" in track:  # (a new track has made none: nothing to look through)
                self._forget_redundant(track["_id"])
            track.update(model=cluster_id, elements=[], last=[], observations=0)
        before = set(track["elements"])
        grown = GraphOfViews.of_sequence([views], after=track["last"])
        track.update(last=views, observations=track["observations"] + 1,
                     seen=track["seen"] + 1, last_seen=time)
        if grown.elements <= before:
            return False
        track["elements"] = sorted(before | grown.elements)
        self.learner.learn(track["model"].binary, GraphOfViews.of(track["elements"]),
                           track["observations"])
        return True

    def _forget_redundant(self, object_id: ObjectId) -> None:
        """Before the object's track begins a model: while it has MODELS_PER_OBJECT, forget
        the one its others explain best (inclusion in their union, eq. 5.2; the oldest of
        equals), so an object seen for months keeps a bounded set of its looks, as varied as
        they were, instead of a new model every OBSERVATIONS_PER_MODEL sightings that no
        entry of MODELS_PER_ENTRY can hold (120 days of a kitchen: 363 entries for 20
        objects). The thesis forgets singletons beyond a limit (algorithm 7) for the same
        reason: a memory the size of the home, not of its history."""
        learner = self.learner
        mine = sorted(m for m, o in self.objects.items() if o == object_id and m in learner.models)
        while len(mine) >= MODELS_PER_OBJECT:
            def explained(m: bytes) -> float:
                others = frozenset().union(*(learner.models[o].graph.elements
                                             for o in mine if o != m))
                return inclusion_degree(learner.models[m].graph, GraphOfViews(others))
            gone = max(mine, key=lambda m: (explained(m), -mine.index(m)))
            learner.forget(gone)
            self.objects.pop(gone)
            self.learnt.pop(gone, None)
            mine.remove(gone)

    def entry_mates(self, object_id: ObjectId) -> list[ObjectId]:
        """The other objects whose tracks made models of the entry the object's current model
        is in (Duceux 6.3: one entry, one object learnt), in the order of their models."""
        track = self.tracks.get(object_id)
        model = track and track.get("model") and track["model"].binary
        entry = self.learner.cluster_of.get(model)
        if entry is None:
            return []
        return [o for o in dict.fromkeys(self.objects.get(m) for m in
                                         sorted(self.learner.members[entry]))
                if o is not None and o != object_id]

    def likeness(self, object_id: ObjectId, mate: ObjectId) -> float:
        """How much of the object's current model the mate's models of its entry hold
        (inclusion, eq. 5.2: 1 when they explain all of it)."""
        model = self.tracks[object_id]["model"].binary
        theirs = [self.learner.models[m].graph.elements
                  for m in self.learner.members[self.learner.cluster_of[model]]
                  if self.objects.get(m) == mate]
        return inclusion_degree(self.learner.models[model].graph,
                                GraphOfViews(frozenset().union(*theirs)))

    def merged(self, keep: ObjectId, twin: ObjectId, stays: ObjectId) -> None:
        """Identity merged object `twin` into `keep` under the id `stays` (one of the two):
        both's models are its, keep's track goes on as its track, and twin's sightings are
        added to it (twin's unfinished model stays as it is: no observation will grow it)."""
        goes = twin if stays == keep else keep
        for model, owner in self.objects.items():
            if owner == goes:
                self.objects[model] = stays
        self.learnt = {m: stays if o == goes else o for m, o in self.learnt.items()}
        self.stage.models.update_many({"map": self.map_name, "object_id": goes},
                                      {"$set": {"object_id": stays}}, session=self.session)
        unread = {keep, twin} - self.tracks.keys()
        if unread:
            self.tracks.update((doc["_id"], doc) for doc in self.stage.tracks.find(
                {"_id": {"$in": list(unread)}}, session=self.session))
        gone = self.tracks.get(twin)
        if gone is None and stays == keep:
            return
        track = self.tracks.pop(keep, None) or {"_id": stays, "map": self.map_name, "seen": 0}
        self.tracks.pop(twin, None)
        self.stage.tracks.delete_one({"_id": goes}, session=self.session)
        self.touched.discard(goes)
        track["_id"] = stays
        if gone is not None:
            track["seen"] += gone["seen"]
            track["last_seen"] = max(track.get("last_seen") or 0, gone.get("last_seen") or 0)
        self.tracks[stays] = track
        self.touched.add(stays)

    def finish(self, version: ObjectId) -> None:
        """Write what the batch learnt (in the batch's transaction, in which identity writes
        `version`)."""
        if self.touched:
            self.stage.tracks.bulk_write([ReplaceOne({"_id": t}, self.tracks[t], upsert=True)
                                          for t in sorted(self.touched)], session=self.session)
        if self.changes:
            self.stage.history.insert_many(self.changes, session=self.session)
        self.stage._write(self.learner, self.objects, self.tracks, self.map_name, self.learnt,
                          self.session, version)
