"""What the camera of a scene could see: a point is in view when it projects into the image in
front of the camera and within the sensor's range (thesis 6.2.1, outOfView)."""

from __future__ import annotations

import numpy as np

from .types import Scene, Vec3

MAX_RANGE = 3.5  # m: a Kinect's depth is unreliable beyond this


def in_view(point: Vec3 | None, scene: Scene, max_range: float = MAX_RANGE) -> bool | None:
    """True or False, or None when the scene does not say where its camera looked."""
    if point is None or scene.camera_pose is None or scene.camera is None:
        return None
    to_camera = np.linalg.inv(scene.camera_pose.matrix())
    x, y, z = (to_camera @ np.array([*point, 1.0]))[:3]
    if not 0.05 < z <= max_range:
        return False
    (fx, fy), (cx, cy) = scene.camera.focal, scene.camera.principal_point
    u, v = fx * x / z + cx, fy * y / z + cy
    return bool(0 <= u < scene.camera.width and 0 <= v < scene.camera.height)
