"""Keeps each map's belief current: for every stored scene, in time order, which object each
cluster is and what became of the objects not seen (thesis 3.2.5 and 6.2; the decision is
identity.resolve). A stage of the memory pipeline (pipeline.py), so it runs exactly once per
scene, live and in a rebuild alike.

`objects` holds one document per physical object believed to exist, in one map:
    {_id, map, name, names, label_weights, state: present | hidden | disappeared, first_seen,
     last_seen (ns), last_scene, last_cluster, views (a cluster per distinct look it was seen
     with, the last one last), view_support and view_seen (per view, how many observations
     showed it and when the last did), position, x, y, region, robot, observations}
`events` holds one document per object per scene that concerned it:
    {_id, map, object_id, scene_id, cluster_id, time (ns), robot, explanation (stay, move,
     newview, appear, hidden, disappear), probability, alternatives [{object_id, explanation,
     probability}], position, region}
`calibration` holds, per map, what the identity model learnt about how alike and how near
two observations of one object are (identity.Calibration), kept with the belief it shaped.

Identity decides on the evidence a cluster arrived with (documents.ARRIVED_KEY): annotations
appended later by enrichment name the object (naming.py) but never change a past decision, so
a rebuild decides exactly as the live pipeline did. Names come from naming.py. A cluster a
person rejected (types/curation.py) is no object: it is left out; a cluster a person said shows
the same object as an earlier one has the two objects merged; a cluster a person said shows
another object than an earlier one is never taken for that one's object, nor merged with it;
such a correction made after its scene was consolidated asks for the map to be rebuilt
(memory/curation.py).
"""

from __future__ import annotations

from collections import Counter, OrderedDict
from collections.abc import Sequence

import numpy as np
from bson import ObjectId
from pymongo import DeleteMany, DeleteOne, ReplaceOne, UpdateMany, UpdateOne

from percept_memory.converters import decode

from . import documents as docs
from .identity import (
    Calibration,
    Decision,
    Explanation,
    Known,
    Observation,
    Parameters,
    declared_spread,
    resolve,
)
from .known_objects import KnownObjects
from .naming import naming_fields, naming_labels, stored_weights
from .schema import CALIBRATION, EVENTS, OBJECTS
from .store import MemoryStore
from .types import Cluster, Scene
from .types.curation import DifferentObject, rejected, same_as, splits
from .view import View

MAX_UNSEEN_CANDIDATES = 32
DECODED_KEPT = 4096
_STATE = {Explanation.HIDDEN: "hidden", Explanation.DISAPPEAR: "disappeared"}
ALTERNATIVES_KEPT = 5
MAX_PLACE_COUNT = 20  # observations an object's place is the mean of, at most
VIEWS_KEPT = 4  # the distinct looks (sides) of an object it is recognised by
# How long an object must have been unseen before the catalogue's word that another object is
# it counts (`_recalled`): within that, identity's places and looks decide alone (the catalogue
# of bench/belief.py's worlds, colours alone, holds objects that only look alike; merging
# them cost strict association on its tune seeds, 95.2 -> 94.2 at sigma 0.025); the kitchen
# weeks' items came back after 1.2 to 61 hours (seeds 0-3).
RECALL_AFTER_NS = 3600 * 10**9
# what identity reads of stored scenes and clusters: no pixels, clouds or logs
SCENE_EVIDENCE = {"images": 0, "clouds": 0, "log": 0, "relations": 0, "annotations": 0,
                  "transforms": 0, docs.SUMMARY_KEY: 0, docs.BLOBS_KEY: 0}
CLUSTER_EVIDENCE = {"hypotheses.crop": 0, "hypotheses.mask": 0, "hypotheses.cloud": 0,
                    docs.SEARCH_KEY: 0}
HYPOTHESIS_EVIDENCE = {key.removeprefix("hypotheses."): 0 for key in CLUSTER_EVIDENCE
                       if key.startswith("hypotheses.")}


def as_evidence(scene: Scene) -> Scene:
    """The scene as identity reads it back (SCENE_EVIDENCE, CLUSTER_EVIDENCE): what the read
    leaves out is at its default. A scene stored in this process is handed over so
    (store.HandedOver), sharing its annotations: the caller must not change them."""
    return scene.model_copy(update={**_left_out(scene, SCENE_EVIDENCE), "clusters": [
        cluster.model_copy(update={"hypotheses": [
            hypothesis.model_copy(update=_left_out(hypothesis, HYPOTHESIS_EVIDENCE))
            for hypothesis in cluster.hypotheses]})
        for cluster in scene.clusters]})


def _left_out(model, projection: dict) -> dict:
    fields = type(model).model_fields
    return {name: fields[name].get_default(call_default_factory=True)
            for name in projection if name in fields}


class Consolidation:
    """The pipeline stage that decides who is who in each scene of a map, in time order."""

    name = "consolidate"
    belief = True

    def __init__(self, store: MemoryStore, params: Parameters | None = None,
                 max_unseen_candidates: int = MAX_UNSEEN_CANDIDATES):
        self.store = store
        self.params = params or Parameters()
        self.max_unseen_candidates = max_unseen_candidates
        self._decoded: OrderedDict = OrderedDict()  # cluster id -> Observation
        # cluster id -> its object by the end of its scene (a later scene of the batch may
        # merge that object into another), for the stages after this one in the batch
        self.decided: dict = {}
        self.created: set = set()  # the objects this batch made: nothing is stored of them
        self._known: dict[str, KnownObjects] = {}  # map -> its objects, as last written
        self._any_split = True  # whether people split any object (the batch's map's objects')
        self.objects = store.db[OBJECTS]
        self.events = store.db[EVENTS]
        self.calibrations = store.db[CALIBRATION]
        # the long-term catalogue (catalogue/stage.py) when identity learns it: scene by scene
        # as identity decides, so that the objects it holds for one are merged (`_recalled`)
        # before the next scene is decided, live and in a rebuild alike, whatever the batching
        self.catalogue = None
        self._learning = None  # the catalogue's batch being learnt (CatalogueStage.begin)

    def apply(self, scene_ids: Sequence[ObjectId], map_name: str, session) -> None:
        stored = self.calibrations.find_one({"_id": map_name}, session=session)
        calibration = self._calibration(stored)
        known = self._known_of(map_name, stored and stored.get("version"), session)
        known.version = ObjectId()  # the version this transaction writes, if it commits
        later = Later(self.objects, self.events, self.store.clusters, session)
        self.decided = {}
        self.created = set()
        if known.any_split is None:  # asked once per map's objects: most stores have none
            known.any_split = self.store.clusters.find_one(ANY_SPLIT, {"_id": 1},
                                                           session=session) is not None
        self._any_split = known.any_split
        learning = self._learning = self.catalogue and self.catalogue.begin(
            map_name, session, stored and stored.get("version"))
        for scene in self._scenes(scene_ids, session):
            self.consolidate(scene, calibration, known, later, session)
            if learning:
                learnt = learning.observe([c.id for c in scene.clusters], scene.timestamp)
                self._recalled(scene, learnt, known, later, session)
        later.write()
        if learning:
            learning.finish(known.version)
        self._learning = None
        self.calibrations.replace_one(
            {"_id": map_name}, {"cues": calibration.to_document(), "version": known.version},
            upsert=True, session=session)

    def _known_of(self, map_name: str, version: ObjectId | None, session) -> KnownObjects:
        """The map's objects in memory, read again unless they are of the stored version."""
        known = self._known.get(map_name)
        if known is None or version is None or known.version != version:
            known = self._known[map_name] = KnownObjects.load(self.objects, map_name, version,
                                                              session)
        return known

    def stored_version(self, map_name: str, session=None) -> ObjectId | None:
        """The version of the map's belief as stored: written with every batch identity
        commits (the catalogue's learner, learnt in the same transactions, is of it too)."""
        stored = self.calibrations.find_one({"_id": map_name}, {"version": 1}, session=session)
        return stored and stored.get("version")

    def reset(self, map_name: str) -> None:
        """Forget the map's objects, their events and what its calibration learnt."""
        ids = self.objects.distinct("_id", {"map": map_name})
        for start in range(0, len(ids), 10_000):
            self.events.delete_many({"object_id": {"$in": ids[start:start + 10_000]}})
        self.objects.delete_many({"map": map_name})
        self.calibrations.delete_one({"_id": map_name})
        self._known.pop(map_name, None)
        if self.catalogue:
            self.catalogue.reset(map_name)

    def calibration(self, map_name: str, session=None) -> Calibration:
        """What the map's identity model has learnt so far (the prior before its first scene)."""
        return self._calibration(self.calibrations.find_one({"_id": map_name},
                                                            session=session))

    def _calibration(self, stored: dict | None) -> Calibration:
        return (Calibration.from_document(stored["cues"]) if stored
                else Calibration.prior(self.params))

    def consolidate(self, scene: Scene, calibration: Calibration, known_objects: KnownObjects,
                    later: Later, session) -> list[Decision]:
        """Decide who is who in one stored scene and record it: the objects in memory at once
        (the next scene's candidates), in the database `later` with its events and cluster
        links."""
        believed = self._candidates(scene, known_objects)
        seen_as = self.observations([c for o, _ in believed for c in _views(o)], session)
        known = [_known(o, in_view, seen_as) for o, in_view in believed
                 if o["last_cluster"] in seen_as]
        kept = [c for c in scene.clusters if not rejected(c.annotations)]
        if not self._any_split and any(splits(c.annotations) for c in scene.clusters):
            self._any_split = known_objects.any_split = True  # (one came with the scene)
        new = [_observation(cluster) for cluster in kept]
        apart = self._kept_apart(scene, kept, later, session)
        decisions = resolve(new, known, self.params, calibration, apart=apart,
                            now=scene.timestamp)
        self._decoded.update((o.key, o) for o in new)  # the next scenes' candidates' evidence
        by_id = {o["_id"]: o for o, _ in believed}
        clusters = {c.id: c for c in kept}
        events, seen_as = [], {}
        links = {c.id: None for c in scene.clusters  # (rejected by a person: no object)
                 if c.id not in clusters and c.object_id is not None}
        for decision in decisions:
            unseen = decision.explanation in (Explanation.HIDDEN, Explanation.DISAPPEAR)
            cluster = None if unseen else clusters.get(decision.key)
            if decision.object is None:  # named by its first observation: the same id when
                object_id = cluster.id  # the map is rebuilt, and its address leads to it later
                self.created.add(object_id)
            else:
                object_id = decision.object
            previous = by_id.get(object_id, {})
            if unseen and previous.get("state") in (_STATE[decision.explanation], "disappeared"):
                continue  # events record changes: still hidden (or still gone) is no news
            events.append(_event(decision, object_id, scene, cluster, previous))
            place = (estimated_place(decision, cluster, previous, self.params, calibration)
                     if cluster else None)
            if cluster is None:  # not seen: hidden or disappeared, where it was
                fields, labels = {"state": _STATE[decision.explanation]}, None
            else:
                fields = _object_fields(decision, scene, cluster, previous, place)
                labels = naming_labels(cluster.annotations)
            known_objects.write(object_id, fields, first_seen=scene.timestamp)
            later.update(object_id, fields, labels, first_seen=scene.timestamp)
            known_objects.places.put(
                object_id, place[0] if place else previous.get("position"),
                live=decision.explanation is not Explanation.DISAPPEAR)
            if cluster is not None:
                links[cluster.id] = object_id
                seen_as[cluster.id] = object_id
        later.add(events, links)
        asked = {c.id: others for c in kept if (others := same_as(c.annotations))}
        if asked:
            later.write()  # the earlier clusters' links are read
        merged: dict = {}  # object -> the object it was merged into
        twins, taken_looks = self._remembered_twice(decisions, clusters, later, session)
        certainty = {d.object: d.probability for d in decisions if d.key in clusters}
        for keep, twin in twins:
            keep, twin = _after(merged, keep), _after(merged, twin)
            if self._seen_together(keep, twin, later):  # (two twins seen side by side)
                continue
            started = max(known_objects.docs.get(o, {}).get("first_seen") or scene.timestamp
                          for o in (keep, twin))  # (the history that began later)
            stays = self._merge(keep, twin, scene, known_objects, later, session)
            merged[twin if stays == keep else keep] = stays
            later.write()  # (that history's first event may be this batch's)
            self._appeared_as_moved(stays, started, certainty.get(keep, 1.0), session)
        absorbed = {twin for _, twin in twins}  # (their looks are the objects' seen now)
        for other, look in taken_looks:
            if other not in absorbed:
                self._forget_look(_after(merged, other), look, known_objects, later)
        for keep, twin in self._asked_to_merge(asked, seen_as, session):
            keep, twin = _after(merged, keep), _after(merged, twin)
            if keep != twin and not self._split_between(keep, twin, later, session):
                stays = self._merge(keep, twin, scene, known_objects, later, session)
                merged[twin if stays == keep else keep] = stays
        self.decided.update((c, _after(merged, o)) for c, o in seen_as.items())
        return decisions

    def _recalled(self, scene: Scene, learnt: list, known: KnownObjects, later: Later,
                  session) -> None:
        """One object remembered as several, which the catalogue learnt as one (Duceux 6.3:
        an entry is an object learnt from all its partial views): an object seen in the scene
        whose model the catalogue just put in an entry with other objects' models is one
        object with each of them that is not in the scene, was never seen together with it
        and no person split from it; they are merged into it, their history kept (e.g. it
        came back after hours, moved, showing a side identity had not linked to it). Only
        after a long absence (RECALL_AFTER_NS): the catalogue remembers what objects look like,
        identity where they have just been."""
        if not learnt:
            return
        seen = {self.decided[c.id] for c in scene.clusters if c.id in self.decided}
        merged: dict = {}
        for object_id in learnt:
            mates = [m for m in self._learning.entry_mates(object_id)
                     if m in known.docs and m not in seen
                     and scene.timestamp - known.docs[m]["last_seen"] >= RECALL_AFTER_NS]
            if object_id not in known.docs or not mates:
                continue
            started = known.docs[object_id]["first_seen"]
            for mate in mates:
                if not (self._seen_together(object_id, mate, later)
                        or self._split_between(object_id, mate, later, session)):
                    likeness = self._learning.likeness(object_id, mate)
                    stays = self._merge(object_id, mate, scene, known, later, session)
                    merged[mate if stays == object_id else object_id] = stays
                    later.write()  # (the track's first event may be this batch's)
                    self._appeared_as_moved(stays, started, likeness, session)
                    object_id = stays
        if merged:
            self.decided.update((c, _after(merged, o)) for c, o in self.decided.items())

    def _appeared_as_moved(self, object_id, started: int, likeness: float, session) -> None:
        """The history joined to an older object's began with an "appear": it was that
        object, moved there unseen. Its probability: for the catalogue's recall, its likeness
        of the two (how much of the new track's model the old one's hold), not a calibrated
        one; for one object remembered twice, that of the link that showed it."""
        self.events.update_one(
            {"object_id": object_id, "time": started, "explanation": Explanation.APPEAR.value},
            {"$set": {"explanation": Explanation.MOVE.value, "probability": likeness,
                      "alternatives": [{"object_id": None,
                                        "explanation": Explanation.APPEAR.value,
                                        "probability": 1 - likeness}]}}, session=session)

    def _asked_to_merge(self, asked: dict, seen_as: dict, session) -> list:
        """(object, the object to merge into it): a cluster of this scene is, a person said,
        the same object as an earlier cluster (types/curation.py: SameObject), whose object
        identity has decided on by now. (Unless a split keeps the two apart: the caller
        asks.)"""
        if not asked:
            return []  # (no round trip: people ask for few scenes)
        earlier = self._objects_of([c for others in asked.values() for c in others], session)
        return [(seen_as[key], earlier[other]) for key, others in asked.items()
                for other in others if earlier.get(other) is not None and key in seen_as]

    def _kept_apart(self, scene: Scene, clusters: list[Cluster], later: Later,
                    session) -> dict:
        """Cluster id -> the objects a person said it is not: those the clusters on the other
        side of a split it is on (types/curation.py: DifferentObject) were taken for in the
        scenes before this one."""
        ids = {c.id for c in clusters}
        others: dict = {}
        for split in self._splits(ids, session):
            one, other = split.sides()
            for side, apart in ((one, other), (other, one)):
                for key in side & ids:
                    others.setdefault(key, set()).update(apart)
        if not others:
            return {}
        later.write()  # the links of this batch's earlier scenes are read
        objects = self._objects_of(list(set().union(*others.values())), session,
                                   before=scene.timestamp)
        return {key: {objects[c] for c in apart if objects.get(c) is not None}
                for key, apart in others.items()}

    def _splits(self, cluster_ids: set, session) -> list[DifferentObject]:
        """The splits in force that name any of these clusters, on either side (few: the
        split indexes hold only the clusters that carry one)."""
        if not self._any_split:
            return []
        found = self.store.clusters.find(naming_splits(cluster_ids), {"annotations": 1},
                                         session=session)
        return [split for doc in found for split in splits(
            decode(a) for a in doc["annotations"] if "author" in a)]

    def _split_between(self, a, b, later: Later, session) -> bool:
        """Whether a person split observations of object `a` from observations of `b` (then
        no merge makes them one object again)."""
        if not self._any_split:
            return False
        later.write()  # the links of this batch's earlier scenes are read
        theirs: dict = {a: set(), b: set()}
        for doc in self.store.clusters.find({"object_id": {"$in": [a, b]}}, {"object_id": 1},
                                            session=session):
            theirs[doc["object_id"]].add(doc["_id"])
        for split in self._splits(theirs[a] | theirs[b], session):
            one, other = split.sides()
            if (one & theirs[a] and other & theirs[b]) or (one & theirs[b] and other & theirs[a]):
                return True
        return False

    def _objects_of(self, cluster_ids: list, session, before: int | None = None) -> dict:
        """Cluster id -> the object identity took it for (None: none, or not decided yet);
        `before`: only the clusters of earlier scenes (during a rebuild, a later one is still
        linked to an object of the belief the rebuild forgot)."""
        earlier = {} if before is None else {"search.time": {"$lt": before}}
        return {doc["_id"]: doc.get("object_id") for doc in self.store.clusters.find(
            {"_id": {"$in": cluster_ids}, **earlier}, {"object_id": 1}, session=session)}

    def _remembered_twice(self, decisions: list[Decision], clusters: dict, later: Later,
                          session) -> list:
        """(object, its twin): an object seen now that looks beyond doubt like another known
        object not seen now, the two never seen together in one scene: one object
        remembered twice (e.g. moved while turned to a side not seen before, then turned
        back). Identical twins never seen side by side are merged too: nobody could tell
        them apart. And (object, look): the lookalikes seen apart, with the look of theirs
        the observation matched."""
        pairs, taken, looks = [], {d.object for d in decisions if d.key in clusters}, []
        for decision in decisions:
            if decision.key not in clusters or decision.object is None:
                continue
            for other, look in decision.lookalikes.items():
                if other not in taken \
                        and not self._seen_together(decision.object, other, later) \
                        and not self._split_between(decision.object, other, later, session):
                    pairs.append((decision.object, other))
                    taken.add(other)
                else:
                    looks.append((other, look))
        return pairs, looks

    @staticmethod
    def _forget_look(object_id, look, known: KnownObjects, later: Later) -> None:
        """A look of an object that another object, seen apart from it, now shows beyond
        doubt, and that it does not show itself now (not its last): it came by a wrong link
        and is forgotten, so it draws no more of the other object's observations. (Identical
        twins each keep the look they were last seen with.)"""
        doc = known.docs.get(object_id)
        if doc is None or look == doc["last_cluster"] or look not in _views(doc):
            return
        fields = _looks_fields([kept for kept in _looks(doc) if kept[0] != look])
        later.update(object_id, fields)  # over its pending looks, if any
        known.write(object_id, fields)

    @staticmethod
    def _seen_together(a, b, later: Later) -> bool:
        return not later.seen_in(a).isdisjoint(later.seen_in(b))

    def _merge(self, keep, twin, scene: Scene, known: KnownObjects, later: Later,
               session) -> ObjectId:
        """One object remembered as two: `twin`'s looks, observations, names and history
        become `keep`'s (the object as `keep` is now), and one of the two ids is no more: the
        one with the shorter history (ties: twin's). Its links are what a merge moves, one
        write per event and per cluster (a long history took 20 ms), and an object known for
        long keeps its id when a short-lived duplicate is found to be it. The id that stays."""
        both = {doc["_id"]: doc for doc in self.objects.find({"_id": {"$in": [keep, twin]}},
                                                             session=session)}
        kept, gone = later.as_written(keep, both.get(keep)), later.as_written(twin, both.get(twin))
        weights = stored_weights(kept) + stored_weights(gone)
        mine = set(_views(kept))
        looks = [look for look in _looks(gone) if look[0] not in mine] + _looks(kept)
        merged = kept | _looks_fields(looks) | naming_fields(weights) | {
            "first_seen": min(kept["first_seen"], gone["first_seen"]),
            "observations": kept.get("observations", 0) + gone.get("observations", 0)}
        stays, goes = ((twin, keep) if gone.get("observations", 0) > kept.get("observations", 0)
                       else (keep, twin))
        merged["_id"] = stays
        self.objects.bulk_write([ReplaceOne({"_id": stays}, merged, upsert=True),
                                 DeleteOne({"_id": goes})], session=session)
        contradicted = self._contradicted(keep, twin, kept, gone, scene, later, session)
        self.events.bulk_write([DeleteMany({"object_id": twin, "scene_id": scene.id}),
                                DeleteMany({"_id": {"$in": contradicted}}),
                                UpdateMany({"object_id": goes}, {"$set": {"object_id": stays}})],
                               session=session)
        self.store.clusters.update_many({"object_id": goes}, {"$set": {"object_id": stays}},
                                        session=session)
        later.merged(stays, goes, twin, scene.id)
        known.drop(goes)
        known.take(merged)  # as just written: no read back
        if self._learning:  # (the catalogue's models of both are the one that stays)
            self._learning.merged(keep, twin, stays)
        return stays

    def _contradicted(self, keep, twin, kept: dict, gone: dict, scene: Scene, later: Later,
                      session) -> list[ObjectId]:
        """The events of one of the two that another of the other contradicts: while both were
        remembered, each scene gave each an event, and one object has one belief a scene. Of
        two in one scene, an observation beats a guess (hidden, disappeared), and of two guesses
        the one of the history observed last by then (where the object was last seen) stays.
        Those pending in the batch are dropped from it; the ids of those stored are returned."""
        since = max(kept["first_seen"], gone["first_seen"])  # the later one's first sighting
        stored = list(self.events.find({"object_id": {"$in": [keep, twin]}, "time": {"$gte": since},
                                        "scene_id": {"$ne": scene.id}},
                                       {"object_id": 1, "scene_id": 1, "time": 1, "cluster_id": 1},
                                       session=session))
        pending = [e for e in later.events if e["object_id"] in (keep, twin)
                   and e["time"] >= since and e["scene_id"] != scene.id]
        by_scene: dict = {}
        for event in sorted(stored + pending, key=lambda e: e["time"]):
            by_scene.setdefault(event["scene_id"], []).append(event)
        observed = {keep: -1, twin: -1}  # each history's last observation so far
        dropped = []
        for events in by_scene.values():
            for event in events:
                if event["cluster_id"] is not None:
                    observed[event["object_id"]] = event["time"]
            guesses = [e for e in events if e["cluster_id"] is None]
            if len({e["object_id"] for e in events}) < 2 or not guesses:
                continue
            if len(guesses) < len(events):  # an observation of the one, a guess of the other
                dropped += guesses
            else:  # two guesses: the one observed earlier goes (ties: the twin's)
                dropped += [min(guesses, key=lambda e: (observed[e["object_id"]],
                                                        e["object_id"] == keep))]
        gone_pending = {id(e) for e in dropped if "_id" not in e}
        later.events = [e for e in later.events if id(e) not in gone_pending]
        return [e["_id"] for e in dropped if "_id" in e]

    def _scenes(self, scene_ids: Sequence[ObjectId], session):
        """The scenes with what identity needs of them (no pixels), in the given order: those
        this process stored handed over, the others read back."""
        scenes = {key: scene for key in scene_ids
                  if (scene := self.store.handed_over.take(key)) is not None}
        if unread := [key for key in scene_ids if key not in scenes]:
            scene_docs = list(self.store.scenes.find({"_id": {"$in": unread}}, SCENE_EVIDENCE,
                                                     session=session))
            cluster_ids = [c for doc in scene_docs for c in doc["clusters"]]
            cluster_docs = list(self.store.clusters.find({"_id": {"$in": cluster_ids}},
                                                         CLUSTER_EVIDENCE, session=session))
            blobs = self.store._blobs(cluster_docs, session)
            scenes |= {doc["_id"]: docs.decode_scene(doc, cluster_docs, blobs)
                       for doc in scene_docs}
        for scene_id in scene_ids:
            if scene_id in scenes:  # (a scene deleted by hand has nothing to consolidate)
                yield scenes[scene_id]

    def observations(self, cluster_ids: list, session=None) -> dict:
        """The evidence of stored clusters (as Observations, by id), decoded once: what a
        cluster arrived with never changes under its id. The catalogue stage learns from the
        same, decoded by the time it runs."""
        missing = [c for c in cluster_ids if c not in self._decoded]
        if missing:
            found = list(self.store.clusters.find({"_id": {"$in": missing}}, CLUSTER_EVIDENCE,
                                                  session=session))
            blobs = self.store._blobs(found, session)
            for doc in found:
                self._decoded[doc["_id"]] = _observation(docs.decode_cluster(doc, blobs))
        while len(self._decoded) > DECODED_KEPT:
            self._decoded.popitem(last=False)
        return {c: self._decoded[c] for c in cluster_ids if c in self._decoded}

    def _candidates(self, scene: Scene, known: KnownObjects) -> list[tuple[dict, bool]]:
        """The objects of the scene's map its clusters may be, with whether their place is in
        view: all believed present or hidden whose place is in view, and the most recently
        seen of the others, disappeared ones included (they may have been moved or brought
        back here). Older unseen objects still persist; they are just not matched now, which
        keeps a scene's cost independent of how many objects the memory holds."""
        seen = known.places.in_view(View(scene))
        in_sight = [(doc, True) for doc in known.get(seen)]
        unseen = [(doc, False) for doc in known.recent(self.max_unseen_candidates, set(seen))]
        # in an order of the stored data's own (not of the objects' ids, made afresh by a
        # rebuild), so that a rebuild decides the same, to the last bit
        return sorted(in_sight, key=lambda c: c[0]["last_cluster"]) + unseen


ANY_SPLIT = {"annotations.split_off": {"$exists": True}}  # (the sparse split_off index)


def naming_splits(cluster_ids) -> dict:
    """The filter of the clusters holding a split that names any of these clusters (schema.py's
    split indexes)."""
    ids = list(cluster_ids)
    return {"$or": [{"annotations.split_off": {"$in": ids}},
                    {"annotations.apart_from": {"$in": ids}}]}


def _known(doc: dict, in_view: bool, seen_as: dict) -> Known:
    """What identity knows of a candidate object: its last look at its estimated place, its
    other looks and when each was last seen."""
    others = [(seen_as[view], seen) for view, _, seen in _looks(doc)
              if view != doc["last_cluster"] and view in seen_as]
    return Known(doc["_id"], _placed(seen_as[doc["last_cluster"]], doc.get("position"),
                                     doc.get("position_variance")),
                 in_view, [o for o, _ in others], doc["last_seen"], [s for _, s in others])


def _after(merged: dict, object_id):
    """The object an object is now, after the merges of a scene so far."""
    while object_id in merged:
        object_id = merged[object_id]
    return object_id


def _observation(cluster: Cluster) -> Observation:
    """What identity compares: the cluster's place and the evidence it arrived with."""
    return Observation(cluster.id, cluster.position,
                       [*cluster.annotations_arrived(), *cluster.hypotheses],
                       cluster.position_variance)


def _event(decision: Decision, object_id, scene: Scene, cluster: Cluster | None,
           previous: dict) -> dict:
    return {
        "map": scene.map,
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


def _views(doc: dict) -> list:
    """The clusters showing each distinct look of an object, the one it was last seen with
    last (older beliefs kept only the last)."""
    return doc.get("views") or [doc["last_cluster"]]


def _looks(doc: dict) -> list[tuple]:
    """An object's looks: (the cluster showing it last, how many observations showed it,
    when the last did); older beliefs kept neither count nor time."""
    views = _views(doc)
    return list(zip(views, doc.get("view_support") or [1] * len(views),
                    doc.get("view_seen") or [doc["last_seen"]] * len(views), strict=True))


def _looks_fields(looks: list[tuple]) -> dict:
    """The looks kept (VIEWS_KEPT): the one seen last, and of the others those most
    observations showed, the newer of equals. A look that only a weak link brought (a
    mistake, maybe) goes first; one that many observations agreed on stays, so one wrong link
    cannot make an object forget how it looks (Duceux 3.4.5: the views of one object are put
    together and recognised as a stream, not one by one; Blodow 6.6: the memory aggregates
    and filters what the observations say)."""
    *older, last = looks
    kept = sorted(range(len(older)), key=lambda k: (older[k][1], k))[-(VIEWS_KEPT - 1):]
    looks = [older[k] for k in sorted(kept)] + [last]
    return {"views": [look[0] for look in looks], "view_support": [look[1] for look in looks],
            "view_seen": [look[2] for look in looks]}


class Later:
    """A batch's object writes, events and cluster links, written together (a few commands
    per batch instead of a few per scene); nothing in a batch reads them before `write` (the
    scenes' candidates are in memory: known_objects.py, and which scenes an object was seen in
    is answered here; what reads links writes them first). A merge takes the two objects'
    pending writes into the object it writes whole, and moves their pending events and links
    here."""

    def __init__(self, objects, events, clusters, session):
        self.targets, self.session = (objects, events, clusters), session
        self.objects: dict = {}  # object id -> its writes so far: Written
        self.events: list[dict] = []
        self.links: dict = {}  # cluster id -> its object (None: none)
        self._seen_in: dict = {}  # object id -> the scenes it was seen in, once asked

    def update(self, object_id, fields: dict, labels: Counter | None = None,
               first_seen: int | None = None) -> None:
        """An object's new fields; when seen (`labels`: the names its observation gave it),
        one observation more, and its first sighting if it is new."""
        written = self.objects.setdefault(object_id, Written())
        written.fields.update(fields)
        if labels is not None:
            written.observations += 1
            written.labels.update(labels)
            if written.first_seen is None:
                written.first_seen = first_seen

    def add(self, events: list[dict], links: dict) -> None:
        self.events += events
        self.links |= links
        for event in events:
            if event["cluster_id"] is not None and event["object_id"] in self._seen_in:
                self._seen_in[event["object_id"]].add(event["scene_id"])

    def seen_in(self, object_id) -> set:
        """The scenes the object was seen in, those of this batch's events too: read once a
        batch (lookalikes are asked about scene after scene), then kept up to date."""
        if object_id not in self._seen_in:
            stored = self.targets[1].distinct("scene_id", {"object_id": object_id,
                                                           "cluster_id": {"$ne": None}},
                                              session=self.session)
            self._seen_in[object_id] = set(stored) | {
                e["scene_id"] for e in self.events
                if e["object_id"] == object_id and e["cluster_id"] is not None}
        return self._seen_in[object_id]

    def as_written(self, object_id, stored: dict | None) -> dict | None:
        """The object as it will be once its pending writes are written (`stored`: as it is
        stored, if it is), which are then forgotten: a merge writes it whole."""
        pending = self.objects.pop(object_id, None)
        return stored if pending is None else pending.applied(object_id, stored)

    def merged(self, stays, goes, twin, scene_id) -> None:
        """A merge: `twin`'s events of the scene are no more, and the events and links of
        `goes` pending are those of `stays` (the merge moves those written)."""
        self.events = [e for e in self.events
                       if e["object_id"] != twin or e["scene_id"] != scene_id]
        for event in self.events:
            if event["object_id"] == goes:
                event["object_id"] = stays
        self.links = {c: stays if o == goes else o for c, o in self.links.items()}
        self._seen_in.pop(stays, None)
        self._seen_in.pop(goes, None)

    def write(self) -> None:
        objects, events, clusters = self.targets
        if self.objects:
            seen = [i for i, written in self.objects.items() if written.observations]
            stored = {doc["_id"]: doc for doc in objects.find(
                {"_id": {"$in": seen}}, {"label_weights": 1}, session=self.session)}
            objects.bulk_write([written.update(object_id, stored.get(object_id, {}))
                                for object_id, written in self.objects.items()],
                               session=self.session)
        if self.events:
            events.insert_many(self.events, session=self.session)
        if self.links:
            clusters.bulk_write([UpdateOne({"_id": c}, {"$set": {"object_id": o}} if o is not None
                                           else {"$unset": {"object_id": ""}})
                                 for c, o in self.links.items()], ordered=False,
                                session=self.session)
        self.objects, self.events, self.links = {}, [], {}


class Written:
    """What a batch wrote of one object: the fields it set, and when it was seen, the
    observations, the names they gave it (added to those stored, which enrichment may have
    changed meanwhile: store.py), and the first sighting (for an object new)."""

    def __init__(self):
        self.fields: dict = {}
        self.observations = 0
        self.labels: Counter = Counter()
        self.first_seen: int | None = None

    def update(self, object_id, stored: dict) -> UpdateOne:
        """The write (`stored`: the object's label weights as stored, if it is)."""
        if not self.observations:
            return UpdateOne({"_id": object_id}, {"$set": self.fields})
        return UpdateOne({"_id": object_id}, {
            "$set": self._set(stored), "$setOnInsert": {"first_seen": self.first_seen},
            "$inc": {"observations": self.observations}}, upsert=True)

    def applied(self, object_id, stored: dict | None) -> dict:
        """The object as the write leaves it (`stored`: as it is stored, if it is)."""
        doc = {"_id": object_id, "first_seen": self.first_seen} | (stored or {})
        doc |= self._set(stored or {})
        if self.observations:
            doc["observations"] = doc.get("observations", 0) + self.observations
        return doc

    def _set(self, stored: dict) -> dict:
        """The fields the write sets: when seen, the names too, over those stored."""
        if not self.observations:
            return self.fields
        weights = stored_weights(stored)
        weights.update(self.labels)
        return {**self.fields, **naming_fields(weights)}


def _placed(last: Observation, place, variance) -> Observation:
    """An object as last seen, at its estimated place (with that estimate's variance)."""
    return last if place is None else last.at(tuple(place),
                                              None if variance is None else tuple(variance))


def estimated_place(decision: Decision, cluster: Cluster, previous: dict, params: Parameters,
                    calibration: Calibration) -> tuple[list | None, int, list | None]:
    """Where an object is, from all its observations since it last moved (their mean: the
    noise of one observation shrinks by the square root of their number), how many, and,
    when the sensor declares its noise, the variance of that mean per axis. A move or a new
    object starts afresh, and so does an observation farther from the mean than one object's
    observations lie apart (3 standard deviations of the same-place spread, declared or
    learnt: a small move taken for a stay); MAX_PLACE_COUNT keeps a slow drift followed."""
    if cluster.position is None:
        return (previous.get("position"), previous.get("place_count", 0),
                previous.get("position_variance"))
    count = previous.get("place_count") or 1
    variance, before = cluster.position_variance, previous.get("position_variance")
    declared = variance is not None and before is not None
    if (decision.explanation in (Explanation.STAY, Explanation.NEWVIEW)
            and previous.get("position") is not None
            and calibration.place.near(cluster.position, previous["position"],
                                       params.proximity_sigma, declared_spread(
                                           np.add(variance, before), params.proximity_sigma)
                                       if declared else None)):
        mean = np.add(np.multiply(previous["position"], count), cluster.position) / (count + 1)
        kept = min(count + 1, MAX_PLACE_COUNT)
        if not declared:
            return mean.tolist(), kept, None
        # the variance of a mean of `count` observations and this one
        spread = (np.multiply(before, count * count) + variance) / (count + 1) ** 2
        return mean.tolist(), kept, spread.tolist()
    return list(cluster.position), 1, None if variance is None else list(variance)


def _object_fields(decision: Decision, scene: Scene, cluster: Cluster, previous: dict,
                   place: tuple) -> dict:
    """What an object seen in a scene is now (its names aside: Later writes them)."""
    looks = _looks(previous) if previous else []
    support = 1 + sum(look[1] for look in looks if look[0] == decision.look)
    looks = [look for look in looks if look[0] != decision.look] + [
        (cluster.id, support, scene.timestamp)]
    position, count, variance = place
    return {
        "map": scene.map, "state": "present", "last_seen": scene.timestamp,
        "last_scene": scene.id, "last_cluster": cluster.id, "robot": scene.robot,
        **_looks_fields(looks),
        "position": position, "place_count": count, "position_variance": variance,
        "x": position[0] if position else None,
        "y": position[1] if position else None, "region": cluster.region,
    }
