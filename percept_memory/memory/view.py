"""What the camera of a scene could see: a point is in view when it lies in the scene's declared
view region, or else projects into the image in front of the camera and within the sensor's
range (thesis 6.2.1, outOfView)."""

from __future__ import annotations

import numpy as np

from .types import Scene

MAX_RANGE = 3.5  # m: a Kinect's depth is unreliable beyond this


class View:
    """The view of one scene's camera, prepared once for testing many points."""

    def __init__(self, scene: Scene, max_range: float = MAX_RANGE):
        self.region = scene.view_region
        self.known = scene.camera_pose is not None and scene.camera is not None
        if self.known:
            self.camera_pose = scene.camera_pose.matrix()
            self.to_camera = np.linalg.inv(self.camera_pose)
            self.camera = scene.camera
        self.max_range = max_range

    def bounds(self) -> tuple[tuple[float, float], tuple[float, float]] | None:
        """A box on the ground plane (x, y) around everything the view can see, for an index
        to find the objects worth testing; None when the scene does not say where it looked."""
        region = self.region
        if region is not None and region.center is not None:
            (x, y, _), r = region.center, region.radius
            return (x - r, y - r), (x + r, y + r)
        if region is not None:
            return tuple(region.box_min[:2]), tuple(region.box_max[:2])
        if not self.known:
            return None
        x, y = self.camera_pose[:2, 3]
        r = self.max_range
        return (float(x - r), float(y - r)), (float(x + r), float(y + r))

    def sees(self, points: np.ndarray) -> np.ndarray:
        """For each point (rows of x, y, z; NaN for an unknown place), whether the view saw its
        place; all False when the scene does not say where its camera looked."""
        points = np.asarray(points, dtype=float).reshape(-1, 3)
        if self.region is not None:
            return self.region.contains(points)
        if not self.known:
            return np.zeros(len(points), dtype=bool)
        local = points @ self.to_camera[:3, :3].T + self.to_camera[:3, 3]
        x, y, z = local.T
        ahead = (z > 0.05) & (z <= self.max_range)
        with np.errstate(divide="ignore", invalid="ignore"):
            (fx, fy), (cx, cy) = self.camera.focal, self.camera.principal_point
            u, v = fx * x / z + cx, fy * y / z + cy
        return ahead & (u >= 0) & (u < self.camera.width) & (v >= 0) & (v < self.camera.height)
