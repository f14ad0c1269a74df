"""Keeps the belief state current: after each stored scene, which object each cluster is and
what became of the objects not seen (thesis 3.2.5 and 6.2; the decision is identity.resolve).

`objects` holds one document per physical object believed to exist:
    {_id, name, names, label_weights, state: present | hidden | disappeared, first_seen,
     last_seen (ns), last_scene, last_cluster, position, region, robot, observations}
`events` holds one document per object per scene that concerned it:
    {_id, object_id, scene_id, cluster_id, time (ns), robot, explanation (stay, move, newview,
     appear, hidden, disappear), probability, alternatives [{object_id, explanation,
     probability}], position, region}
`calibration` holds what the identity model learnt about how alike and how near two
observations of one object are (identity.Calibration), kept with the belief it shaped.
Names come from the words annotators gave the object, weighted by how much each annotation
type names rather than describes it (thesis 5.4.5: word statistics), so "the ketchup" finds
the object a Heinz logo and a "ketchup" classification were seen on.
"""

from __future__ import annotations

from collections import Counter, OrderedDict
from collections.abc import Sequence

from bson import ObjectId
from pymongo import UpdateOne
from pymongo.cursor import Cursor

from percept_memory.converters import escape_key, unescape_key

from .identity import (
    Calibration,
    Decision,
    Explanation,
    Known,
    Observation,
    Parameters,
    resolve,
)
from .schema import CALIBRATION, EVENTS, OBJECTS
from .store import MemoryStore
from .types import Annotation, Cluster, Scene
from .view import View

NAMES_KEPT = 3
MAX_UNSEEN_CANDIDATES = 32
DECODED_KEPT = 4096
_STATE = {Explanation.HIDDEN: "hidden", Explanation.DISAPPEAR: "disappeared"}
ALTERNATIVES_KEPT = 5


class Consolidator:
    """An after-store stage of the ingest service: consolidates every new scene, in time order."""

    def __init__(self, store: MemoryStore, params: Parameters | None = None,
                 max_unseen_candidates: int = MAX_UNSEEN_CANDIDATES):
        self.store = store
        self.params = params or Parameters()
        self.max_unseen_candidates = max_unseen_candidates
        self._decoded: OrderedDict = OrderedDict()  # cluster id -> Observation
        self.objects = store.db[OBJECTS]
        self.events = store.db[EVENTS]
        self.calibrations = store.db[CALIBRATION]
        stored = self.calibrations.find_one({"_id": CALIBRATION})
        self.calibration = (Calibration.from_document(stored["cues"]) if stored
                            else Calibration.prior(self.params))

    def __call__(self, scenes: Sequence[Scene]) -> None:
        for scene in sorted(scenes, key=lambda s: s.timestamp):
            self.consolidate(scene)

    def consolidate(self, scene: Scene) -> list[Decision]:
        """Decide who is who in one stored scene and record it."""
        believed = self._candidates(scene)
        last = self._observations([o["last_cluster"] for o, _ in believed])
        known = [Known(o["_id"], last[o["last_cluster"]], seen)
                 for o, seen in believed if o["last_cluster"] in last]
        believed = [o for o, _ in believed]
        new = [_observation(cluster) for cluster in scene.clusters]
        decisions = resolve(new, known, self.params, self.calibration)
        by_id = {o["_id"]: o for o in believed}
        clusters = {c.id: c for c in scene.clusters}
        objects, events, links = [], [], []
        for decision in decisions:
            unseen = decision.explanation in (Explanation.HIDDEN, Explanation.DISAPPEAR)
            cluster = None if unseen else clusters.get(decision.key)
            object_id = decision.object if decision.object is not None else ObjectId()
            previous = by_id.get(object_id, {})
            if unseen and previous.get("state") in (_STATE[decision.explanation], "disappeared"):
                continue  # events record changes: still hidden (or still gone) is no news
            events.append(_event(decision, object_id, scene, cluster, previous))
            objects.append(_object_update(object_id, decision, scene, cluster, previous))
            if cluster is not None:
                links.append(UpdateOne({"_id": cluster.id}, {"$set": {"object_id": object_id}}))
                cluster.object_id = object_id

        def work(session):
            if objects:
                self.objects.bulk_write(objects, session=session)
                self.events.insert_many(events, session=session)
            if links:
                self.store.clusters.bulk_write(links, session=session)
            self.calibrations.replace_one(
                {"_id": CALIBRATION}, {"cues": self.calibration.to_document()}, upsert=True,
                session=session)

        self.store._transaction(work)
        return decisions

    def _observations(self, cluster_ids: list) -> dict:
        """The evidence of stored clusters, decoded once: an observation does not change under
        its id (an annotation appended later is seen when its object is next observed)."""
        missing = [c for c in cluster_ids if c not in self._decoded]
        for cluster_id, cluster in self.store.get_clusters(missing).items():
            self._decoded[cluster_id] = _observation(cluster)
        while len(self._decoded) > DECODED_KEPT:
            self._decoded.popitem(last=False)
        return {c: self._decoded[c] for c in cluster_ids if c in self._decoded}

    def _candidates(self, scene: Scene) -> list[tuple[dict, bool]]:
        """The objects this scene's clusters may be, with whether their place is in view: all
        believed present or hidden whose place is in view, and the most recently seen of the
        others, disappeared ones included (they may have been moved or brought back here).
        Older unseen objects still persist; they are just not matched now, which keeps a
        scene's cost independent of how many objects the memory holds."""
        in_sight = []
        view = View(scene)
        bounds = view.bounds()
        if bounds is not None:
            for doc in self.objects_near(bounds):
                if view.sees(_vec(doc.get("position"))):
                    in_sight.append((doc, True))
        seen = {doc["_id"] for doc, _ in in_sight}
        recent = self.objects.find({"_id": {"$nin": list(seen)}}).sort("last_seen", -1)
        unseen = [(doc, False) for doc in recent.limit(self.max_unseen_candidates)]
        return in_sight + unseen

    def objects_near(self, bounds) -> Cursor:
        """The objects believed present or hidden whose x, y lie in a box ((x0, y0), (x1, y1)),
        by the index on their place."""
        query = {"state": {"$ne": "disappeared"}, "xy": {"$geoWithin": {"$box": bounds}}}
        return self.objects.find(query).hint("xy_state")

    def rebuild(self, progress=None) -> int:
        """Forget the belief state and consolidate every stored scene again in time order
        (after a parameter change): deterministic for the same store and parameters."""
        self.objects.delete_many({})
        self.events.delete_many({})
        self.calibrations.delete_many({})
        self.calibration = Calibration.prior(self.params)
        self.store.clusters.update_many({}, {"$set": {"object_id": None}})
        count = 0
        for doc in self.store.scenes.find({}, {"_id": 1}).sort([("timestamp", 1), ("_id", 1)]):
            self.consolidate(self.store.get_scene(doc["_id"]))
            count += 1
            if progress:
                progress()
        return count


def _vec(value) -> tuple | None:
    return tuple(value) if value is not None else None


def _observation(cluster: Cluster) -> Observation:
    return Observation(cluster.id, cluster.position, [*cluster.annotations, *cluster.hypotheses])


def _event(decision: Decision, object_id, scene: Scene, cluster: Cluster | None,
           previous: dict) -> dict:
    return {
        "object_id": object_id,
        "scene_id": scene.id,
        "cluster_id": cluster.id if cluster else None,
        "time": scene.timestamp,
        "robot": scene.robot,
        "explanation": decision.explanation.value,
        "probability": decision.probability,
        "alternatives": [
            {"object_id": a.object, "explanation": a.explanation.value,
             "probability": a.probability}
            for a in decision.alternatives[:ALTERNATIVES_KEPT]
        ],
        "position": list(cluster.position) if cluster and cluster.position else previous.get(
            "position"),
        "region": cluster.region if cluster else previous.get("region"),
    }


def _object_update(object_id, decision: Decision, scene: Scene, cluster: Cluster | None,
                   previous: dict) -> UpdateOne:
    if cluster is None:  # not seen: hidden or disappeared, where it was
        return UpdateOne({"_id": object_id}, {"$set": {"state": _STATE[decision.explanation]}})
    weights = Counter({unescape_key(k): v for k, v in previous.get("label_weights", {}).items()})
    weights.update(naming_labels(cluster))
    names = [name for name, _ in weights.most_common(NAMES_KEPT)]
    return UpdateOne(
        {"_id": object_id},
        {
            "$set": {
                "state": "present", "last_seen": scene.timestamp, "last_scene": scene.id,
                "last_cluster": cluster.id, "robot": scene.robot,
                "position": list(cluster.position) if cluster.position else None,
                "xy": list(cluster.position[:2]) if cluster.position else None,
                "region": cluster.region, "names": names, "name": names[0] if names else None,
                "label_weights": {escape_key(k): v for k, v in weights.items()},
            },
            "$setOnInsert": {"first_seen": scene.timestamp},
            "$inc": {"observations": 1},
        },
        upsert=True,
    )


def naming_labels(cluster: Cluster) -> Counter:
    """The words a cluster's annotations name its object by, with their weights."""
    found: Counter = Counter()
    for annotation in cluster.annotations:
        if isinstance(annotation, Annotation) and annotation.naming_weight:
            for label in annotation.labels():
                if label:
                    found[label.strip().casefold()] += annotation.naming_weight
    return found
