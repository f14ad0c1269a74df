"""Where a map's objects are believed to be, held in memory by the consolidator working on the
map: finding the objects a view may contain is then one vectorised test instead of a database
query per scene (bench/pipeline.py: ~700 objects read per scene in a crowded map).

The copy is trusted only while the map's belief carries the version the copy was left at.
Every consolidation writes a new version in its transaction (consolidation.py), so a copy that
missed a write, by another consolidator, a rebuild or a transaction that did not commit, is
read again from the database."""

from __future__ import annotations

import numpy as np
from bson import ObjectId
from pymongo.collection import Collection

from .view import View


class Places:
    """The places of a map's objects that are believed present or hidden (not disappeared)."""

    def __init__(self, version: ObjectId | None):
        self.version = version
        self.rows: dict[ObjectId, int] = {}
        self.ids: list[ObjectId] = []
        self.xyz = np.empty((64, 3))
        self.live = np.zeros(64, dtype=bool)

    @classmethod
    def load(cls, objects: Collection, map_name: str, version: ObjectId | None,
             session=None) -> Places:
        places = cls(version)
        for doc in objects.find({"map": map_name, "state": {"$ne": "disappeared"}},
                                {"position": 1}, session=session):
            places.put(doc["_id"], doc.get("position"), live=True)
        return places

    def put(self, object_id: ObjectId, position, live: bool) -> None:
        """An object's new place (None: unknown) and whether it is still believed there."""
        row = self.rows.get(object_id)
        if row is None:
            if not live:
                return
            row = self.rows[object_id] = len(self.ids)
            self.ids.append(object_id)
            if row == len(self.live):  # room for twice as many
                self.xyz = np.concatenate([self.xyz, np.empty_like(self.xyz)])
                self.live = np.concatenate([self.live, np.zeros_like(self.live)])
        self.xyz[row] = position if position is not None else np.nan
        self.live[row] = live

    def in_view(self, view: View) -> list[ObjectId]:
        """The objects whose place the view saw."""
        bounds = view.bounds()
        if bounds is None:
            return []
        (x0, y0), (x1, y1) = bounds
        xyz = self.xyz[:len(self.ids)]
        x, y = xyz[:, 0], xyz[:, 1]
        rows = np.flatnonzero(self.live[:len(self.ids)] & (x >= x0) & (x <= x1)
                              & (y >= y0) & (y <= y1))
        return [self.ids[row] for row in rows[view.sees(xyz[rows])]]
