"""A scene in 3D, in the scene's frame: its points, its clusters' boxes and its camera's
frustum, as a viewer draws them.

The points are the scene's clouds, else its depth image seen from its camera, else its
clusters' own points; a viewer gets at most `max_points` of them, an even random sample
(the same every time), since a depth image alone holds 300 000.
"""

from __future__ import annotations

import numpy as np
from pydantic import BaseModel

from percept_memory.memory.types import Cluster, Geometry, PointCluster, Scene, Vec3
from percept_memory.memory.view import MAX_RANGE

MAX_POINTS = 200_000
MARKER = 0.03  # m: half the side of the box drawn for a cluster known only by its position
NEAREST, FAR = 0.3, 1.0  # m: the frustum's depth bounds when no cluster says how far to draw


class Box(BaseModel):
    """A cluster's axis-aligned box, numbered as on the scene page (from 1)."""

    number: int
    low: Vec3
    high: Vec3


class Shapes(BaseModel):
    """What is drawn besides the points: boxes, and the frustum as its apex (the camera)
    followed by its far corners (image corners (0, 0), (w, 0), (w, h), (0, h))."""

    frame: str
    points: int  # how many points the scene has (before any sampling)
    boxes: list[Box]
    frustum: list[Vec3] | None = None


def shapes(scene: Scene) -> Shapes:
    boxes = []
    for number, cluster in enumerate(scene.clusters, 1):
        extent = _extent(scene, cluster)
        if extent is not None:
            boxes.append(Box(number=number, low=tuple(extent[0]), high=tuple(extent[1])))
    return Shapes(frame=scene.frame, points=len(_cloud(scene)[0]), boxes=boxes,
                  frustum=_frustum(scene, boxes))


def points(scene: Scene, max_points: int = MAX_POINTS) -> tuple[np.ndarray, np.ndarray]:
    """At most max_points of the scene's points: (N, 3) float32 positions and (N, 3) uint8
    colours (red, green, blue; grey where the sensor gave none)."""
    xyz, bgr = _cloud(scene)
    finite = np.isfinite(xyz).all(axis=1)
    xyz, bgr = xyz[finite], bgr[finite]
    if len(xyz) > max_points:
        kept = np.sort(np.random.default_rng(0).choice(len(xyz), max_points, replace=False))
        xyz, bgr = xyz[kept], bgr[kept]
    return xyz.astype(np.float32), np.ascontiguousarray(bgr[:, ::-1])


def _cloud(scene: Scene) -> tuple[np.ndarray, np.ndarray]:
    """All the scene's points, (N, 3) in its frame, and their BGR colours."""
    if scene.clouds:
        xyz = np.concatenate([cloud.xyz() for cloud in scene.clouds.values()])
        colours = [cloud.bgr() for cloud in scene.clouds.values()]
        return xyz, (np.concatenate(colours) if all(c is not None for c in colours)
                     else _grey(len(xyz)))
    depth = _depth(scene)
    if depth is not None:
        v, u = np.nonzero(depth)
        pose = scene.camera_pose.matrix()
        xyz = scene.camera.back_project(u, v, depth[v, u]) @ pose[:3, :3].T + pose[:3, 3]
        colour = scene.images.get("color")
        usable = colour is not None and colour.data.ndim == 3 and \
            colour.data.shape[:2] == depth.shape
        return xyz, colour.data[v, u, :3] if usable else _grey(len(xyz))
    own = [h.points.xyz() for c in scene.clusters
           if (h := c.hypothesis_of(PointCluster)) is not None and h.points is not None]
    xyz = np.concatenate(own) if own else np.empty((0, 3))
    return xyz, _grey(len(xyz))


def _grey(count: int) -> np.ndarray:
    return np.full((count, 3), 128, np.uint8)


def _depth(scene: Scene) -> np.ndarray | None:
    """The depth image in metres (0 where there is no depth), if the scene has one and says
    where its camera was."""
    image = scene.images.get("depth")
    if image is None or scene.camera is None or scene.camera_pose is None:
        return None
    depth = image.data.astype(float)
    if image.data.dtype.kind in "iu":  # ROS 16UC1: millimetres
        depth /= 1000.0
    return np.where(np.isfinite(depth) & (depth > 0), depth, 0.0)


def _extent(scene: Scene, cluster: Cluster) -> tuple[np.ndarray, np.ndarray] | None:
    """A cluster's box: around its points, else its size around its position, else a small
    marker at its position; None when it has no place."""
    points = cluster.hypothesis_of(PointCluster)
    if points is not None:
        xyz = points.points.xyz() if points.points is not None else _indexed(scene, points)
        xyz = xyz[np.isfinite(xyz).all(axis=1)]
        if len(xyz):
            return xyz.min(axis=0), xyz.max(axis=0)
    if cluster.position is None:
        return None
    centre = np.array(cluster.position)
    size = next((np.array(g.size) for g in cluster.annotations_of(Geometry) if g.size), None)
    half = size / 2 if size is not None else np.full(3, MARKER)
    return centre - half, centre + half


def _indexed(scene: Scene, points: PointCluster) -> np.ndarray:
    cloud = scene.clouds.get(points.cloud)
    if cloud is None:
        return np.empty((0, 3))
    indices = points.indices.astype(np.int64).ravel()
    return cloud.xyz()[indices[(indices >= 0) & (indices < len(cloud.points))]]


def _frustum(scene: Scene, boxes: list[Box]) -> list[Vec3] | None:
    """The camera's view out to its farthest cluster (FAR without any), up to MAX_RANGE."""
    if scene.camera is None or scene.camera_pose is None:
        return None
    pose = scene.camera_pose.matrix()
    to_camera = np.linalg.inv(pose)
    centres = np.array([np.add(b.low, b.high) / 2 for b in boxes]).reshape(-1, 3)
    depths = centres @ to_camera[2, :3] + to_camera[2, 3]  # along the optical axis
    far = float(np.clip(depths.max(initial=0) + 0.1, NEAREST, MAX_RANGE)) if len(boxes) else FAR
    width, height = scene.camera.width, scene.camera.height
    corners = scene.camera.back_project(np.array([0, width, width, 0]),
                                        np.array([0, 0, height, height]), np.full(4, far))
    ends = [pose[:3, 3], *(corners @ pose[:3, :3].T + pose[:3, 3])]
    return [tuple(float(c) for c in end) for end in ends]
