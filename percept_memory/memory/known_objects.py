"""A map's objects as the consolidator holding the map's lease knows them, in memory between
scenes: what deciding reads of each object (its place, looks, state, when it was last seen)
and where each is (places.py). A scene's candidates then cost no query, and the object
writes of a batch of scenes go to the database together (consolidation.Later) instead of one
command per scene (bench/pipeline.py: two queries and a write per scene were a third of a
kitchen scene's time).

The copy is trusted only while the map's belief carries the version it was left at, as the
places are: every consolidation writes a new version in its transaction, so a copy that missed
a write (by another consolidator, a rebuild, a transaction that did not commit or was tried
again) is read again from the database. The objects' names are not kept: enrichment renames
objects outside the lease (store.py), so they are read when the batch's writes are."""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Iterable

from bson import ObjectId
from pymongo.collection import Collection

from .places import Places

# what deciding reads of an object: its candidate fields but its names
FIELDS = ("state", "position", "place_count", "position_variance", "region", "last_cluster",
          "last_seen", "first_seen", "views", "view_support", "view_seen")


def _recency(doc: dict) -> tuple:
    """The order of the objects' map_seen index, oldest first (last seen, then last cluster)."""
    return doc["last_seen"], doc["last_cluster"]


class KnownObjects:
    """The objects of one map: their fields (FIELDS, by id), their places, and the order they
    were last seen in."""

    def __init__(self, version: ObjectId | None):
        self.places = Places(version)
        self.docs: dict[ObjectId, dict] = {}
        # ids, least recently seen first (those seen at the same time in any order)
        self._order: OrderedDict = OrderedDict()
        self._in_order = True  # False when a put came out of order: sorted when next read
        # whether people split any objects (None: not asked yet), kept as long as these are:
        # a split made later rebuilds its map, or comes with a scene (consolidation.py)
        self.any_split: bool | None = None

    @property
    def version(self) -> ObjectId | None:
        return self.places.version

    @version.setter
    def version(self, version: ObjectId) -> None:
        self.places.version = version

    @classmethod
    def load(cls, objects: Collection, map_name: str, version: ObjectId | None,
             session=None) -> KnownObjects:
        known = cls(version)
        for doc in objects.find({"map": map_name}, dict.fromkeys(FIELDS, 1), session=session):
            known.take(doc)
        return known

    def take(self, doc: dict) -> None:
        """An object as the database holds it now (its FIELDS), with its place."""
        self.put({k: v for k, v in doc.items() if k == "_id" or k in FIELDS})
        self.places.put(doc["_id"], doc.get("position"), live=doc["state"] != "disappeared")

    def write(self, object_id: ObjectId, fields: dict, first_seen: int | None = None
              ) -> None:
        """Fields written to an object (`first_seen`: when it was, if it is new)."""
        doc = self.docs.get(object_id) or {"_id": object_id, "first_seen": first_seen}
        doc = doc | {k: v for k, v in fields.items() if k in FIELDS}
        if "last_seen" in fields:
            self.put(doc)
        else:
            self.docs[object_id] = doc

    def put(self, doc: dict) -> None:
        """An object as its document in the database holds it now, just seen."""
        object_id = doc["_id"]
        self._order.pop(object_id, None)
        if self._order:  # still in time order if seen after the newest of the others
            newest = self.docs[next(reversed(self._order))]
            self._in_order &= newest["last_seen"] <= doc["last_seen"]
        self.docs[object_id] = doc
        self._order[object_id] = None

    def drop(self, object_id: ObjectId) -> None:
        """An object that is no more (merged into another)."""
        self.docs.pop(object_id, None)
        self._order.pop(object_id, None)
        self.places.put(object_id, None, live=False)

    def get(self, ids: Iterable[ObjectId]) -> list[dict]:
        return [self.docs[i] for i in ids if i in self.docs]

    def recent(self, limit: int, but: set) -> list[dict]:
        """The `limit` objects seen most recently, but these, newest first (as the map_seen
        index gives them: last seen, then last cluster, descending)."""
        if not self._in_order:
            for object_id in sorted(self._order, key=lambda i: _recency(self.docs[i])):
                self._order.move_to_end(object_id)
            self._in_order = True
        picked: list[dict] = []
        for object_id in reversed(self._order):
            if object_id in but:
                continue
            doc = self.docs[object_id]
            if len(picked) >= limit and doc["last_seen"] < picked[-1]["last_seen"]:
                break  # (those seen at the same time as the last taken are ordered below)
            picked.append(doc)
        return sorted(picked, key=_recency, reverse=True)[:limit]
