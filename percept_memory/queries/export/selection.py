"""The clusters an export selects, a page at a time, grouped by scene.

Pages come from the query engine's own cluster query (oldest first, resumed by its cursor),
so an export selects exactly what `clusters` would answer, and each page is one bounded read:
memory holds a page, never the whole selection. All clusters of a scene share the scene's
time, so a scene is complete once the time moves on; only the clusters of the last instant of
a page wait for the next page.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from itertools import groupby

from bson import ObjectId

from percept_memory.converters import DecodeContext, decode, escape_key
from percept_memory.memory import documents as docs
from percept_memory.memory.schema import CLUSTERS, OBJECTS, SCENES
from percept_memory.memory.store import MemoryStore
from percept_memory.memory.types import Cluster, ImageROI, Scene
from percept_memory.queries.clusters import compiled, find_clusters
from percept_memory.queries.model import ClusterQuery
from percept_memory.queries.ops import Count, Runner

from .model import ExportQuery, ImageMode

PAGE = 200
SCENE_FIELDS = ("_type", "timestamp", "robot", "frame", "camera_pose", "camera")


@dataclass
class SceneGroup:
    """One scene (without its clusters; with the images the clusters' boxes refer to, when
    asked) and its selected clusters, in id order, with the names of their objects."""

    scene: Scene
    clusters: list[Cluster]
    object_names: dict[ObjectId, str]


class Selection:
    """The clusters of an export query, read with the engine's time limit per operation."""

    def __init__(self, store: MemoryStore, query: ExportQuery, limit_ms: int,
                 pixels: ImageMode | None):
        self.store, self.query, self.pixels = store, query, pixels
        self.runner = Runner(store.db, limit_ms)
        self.pages = ClusterQuery(**dict(query.cluster_filter()), sort="oldest", limit=PAGE)

    def count(self) -> int:
        """How many clusters are selected, at most the export's limit (also checks the query
        can run: a text without words, say, fails here, before anything is written)."""

        def plan():
            match, _ = yield from compiled(self.query)
            return (yield Count(CLUSTERS, match))

        total = self.runner.run(plan())
        return total if self.query.limit is None else min(total, self.query.limit)

    def groups(self) -> Iterator[SceneGroup]:
        """The scenes in time order, each with its selected clusters (read a page at a time as
        the caller goes on: an export stops once it has its limit of labelled clusters)."""
        waiting: list[tuple[int, Cluster]] = []
        for page, last in self._pages():
            ready = waiting + page
            waiting = [] if last else _last_instant(ready)
            yield from self._grouped([c for _, c in ready[:len(ready) - len(waiting)]])

    def _pages(self) -> Iterator[tuple[list[tuple[int, Cluster]], bool]]:
        """Pages of (time, whole cluster) in time, then id order, and whether it is the last."""
        query = self.pages
        while True:
            found = self.runner.run(find_clusters(query))
            by_id = self.store.get_clusters([hit.id for hit in found.items])
            last = found.next is None
            yield [(hit.time, by_id[hit.id]) for hit in found.items if hit.id in by_id], last
            if last:
                return
            query = query.model_copy(update={"cursor": found.next})

    def _grouped(self, clusters: list[Cluster]) -> Iterator[SceneGroup]:
        if not clusters:
            return
        scenes = self._scenes(clusters)
        names = self._object_names(clusters)
        order = {scene_id: i for i, scene_id in enumerate(dict.fromkeys(
            c.scene_id for c in clusters))}  # scenes of one instant, in order of first cluster
        for scene_id, members in groupby(sorted(clusters, key=lambda c: order[c.scene_id]),
                                         key=lambda c: c.scene_id):
            if scene_id in scenes:
                yield SceneGroup(scenes[scene_id], list(members), names)

    def _scenes(self, clusters: list[Cluster]) -> dict[ObjectId, Scene]:
        """The scenes of the clusters, without clouds and clusters, with the images the
        clusters' boxes are in: all of them for scene images (where the scene has them), for
        crops those of the clusters that have no crop stored (it is cut from the image)."""
        projection = dict.fromkeys(SCENE_FIELDS, 1)
        for cluster in clusters:
            rois = [h for h in cluster.hypotheses if isinstance(h, ImageROI)]
            if self.pixels in ("auto", "scenes") or (self.pixels == "crops" and
                                                     all(roi.crop is None for roi in rois)):
                projection |= {f"images.{escape_key(roi.image)}": 1 for roi in rois}
        found = list(self.store.db[SCENES].find(
            {"_id": {"$in": list({c.scene_id for c in clusters})}}, projection))
        blobs = self.store.get_blobs(docs.blob_ids(found))
        return {doc["_id"]: decode(doc, DecodeContext(blobs)) for doc in found}

    def _object_names(self, clusters: list[Cluster]) -> dict[ObjectId, str]:
        if self.query.label != "object":
            return {}
        ids = list({c.object_id for c in clusters if c.object_id is not None})
        return {doc["_id"]: doc["name"] for doc in self.store.db[OBJECTS].find(
            {"_id": {"$in": ids}, "name": {"$ne": None}}, {"name": 1})}


def _last_instant(timed: list[tuple[int, Cluster]]) -> list[tuple[int, Cluster]]:
    """The clusters at the time of the last one: their scene may go on in the next page."""
    keep = len(timed)
    while keep and timed[keep - 1][0] == timed[-1][0]:
        keep -= 1
    return timed[keep:]
