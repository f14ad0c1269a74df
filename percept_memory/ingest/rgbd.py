"""RGB-D samples importer: RoboSherlock's `samples/` folders as Scenes.

Three layouts (LAYOUTS), found anywhere under the folder given:

(a) `rgb_<stamp>.png` + `depth_<stamp>.png` (16-bit, millimetres, registered to the RGB image)
    + `viewpoint_<stamp>.vp` (the camera in the map frame and the time of that pose). The
    scene is in the map frame at `<stamp>` (ns), which pairs the three files. Objects: the
    depth is back-projected with the camera intrinsics, the supporting surface found by RANSAC
    (a horizontal plane in the map), and the points above it clustered; region "counter_top".
(b) `cloud<n>.pcd` + `image<n>.png` (+ `ground_truth<n>.lbl`). There is no viewpoint and no
    recording time. The clouds are not in the camera frame (projected with the Kinect
    intrinsics they miss the image by up to 100 px), so the camera is found in the cloud's
    frame by registration: SIFT matches between a rendering of the coloured cloud and the
    image, then PnP (when that fails, the PCD's VIEWPOINT, identity in practice, is used and a
    warning logged). The scene frame is "cloud", the camera pose that estimate. Objects: the
    ground-truth segments when labelled (but the largest one if it is planar: the table;
    low_noise's clouds are cut to the objects, so none is), else plane fit + clustering as in
    (a); region "table".
(c) `test_point_cloud_<n>.pcd` + `test_rgb_image_<n>.png` + `test_viewpoint_<n>.vp`
    (RoboSherlock's own test sample): read as (b), at the time of the viewpoint's stamp (its
    pose is the camera's in the map; how the cloud's frame lies in the map the files do not
    say, so the scene stays in the cloud's frame).

A time is never invented: (a) and (c) are at the time their files record; (b) records none, so
its samples are at the time given (`time`, then a second apart in file order) or else at their
cloud file's modification time (the same on every import of the same files; a copy of the
folder has new file times). `Samples.times` says which, for the import summary to show.

The intrinsics are the Kinect's (525 px focal length at 640x480), scaled to the image's size
when it is another: the same lens read out at another resolution.

Every object becomes a Cluster with an ImageROI (box, full-resolution mask, crop, pHash), a
PointCluster (its points in the map for (a), indices into the scene cloud for (b), (c)), a
ColorHistogram, a Location (centroid in the scene frame) and a Geometry (bounding box).
"""

from __future__ import annotations

import configparser
import itertools
import re
from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from time import perf_counter

import cv2
import imagehash
import numpy as np
from numpy.lib.recfunctions import repack_fields
from PIL import Image as PILImage
from pydantic import ValidationError
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import ConvexHull, QhullError, cKDTree
from scipy.spatial.transform import Rotation

from percept_memory.ingest.errors import SourceError
from percept_memory.ingest.service import in_map
from percept_memory.ingest.synthetic import KINECT
from percept_memory.memory.errors import problems_line
from percept_memory.memory.types import (
    CameraInfo,
    Cluster,
    ColorHistogram,
    Geometry,
    Image,
    ImageROI,
    Location,
    LogLine,
    PointCloud,
    PointCluster,
    Pose,
    Scene,
    Transform,
)

SOURCE = "RGBDImporter"
LAYOUTS = ("rgb_<stamp>.png + depth_<stamp>.png + viewpoint_<stamp>.vp",
           "cloud<n>.pcd + image<n>.png (+ ground_truth<n>.lbl)",
           "test_point_cloud_<n>.pcd + test_rgb_image_<n>.png + test_viewpoint_<n>.vp")
SECOND = 10**9
# How a scene's time was found (Samples.times).
STAMPED = "the stamps of the file names"
VIEWPOINT_STAMPS = "the stamps of the viewpoint files"
GIVEN = "the time given, a second apart"
FILE_TIMES = "the modification times of the cloud files"

# Segmentation. Kinect depth noise on the counter is ~3.5 mm (std) at 1-1.5 m.
PLANE_SAMPLE = 4000  # RANSAC runs on this many random points (the counter is a third)
PLANE_ITERATIONS = 300
PLANE_TOLERANCE = 0.015  # m, inlier distance (about 4 sigma of the noise)
# Share of the points a plane must hold to be the supporting surface. A horizontal one (layout
# a knows which way is up) is the counter or the floor. Without gravity (layout b) planes cut
# through a pile of objects hold 20-25% of a cloud cut to the objects, as low_noise's are.
MIN_PLANE_SHARE = {"horizontal": 0.1, "any": 0.3}
MAX_TILT = 15.0  # degrees between the map's z axis and the counter's normal
HEIGHT_BAND = (0.01, 0.5)  # m above the plane: above the noise, up to the tallest object
HULL_MARGIN = 0.02  # m inside the surface's outline: walls and cabinets rise at its edges
VOXEL = 0.01  # m, clustering runs on one point per voxel; masks use every point
CLUSTER_TOLERANCE = 0.02  # m, Euclidean clustering distance
MIN_CLUSTER_VOXELS = 15  # ~15 cm^2 of surface: fewer is noise
MAX_CLUSTER_EXTENT = 0.5  # m: longer is furniture at the surface's edge, not an object on it
BACKGROUND_PLANARITY = 0.9  # a labelled segment this planar (and the largest) is the table

# Registration of a cloud to its image (layout b).
START_ANGLES = (0.0, 15.0, -15.0, 30.0, -30.0)  # degrees, views around the cloud tried first
MIN_START_INLIERS = 15  # PnP inliers for a start view to be refined
MIN_INLIERS = 20  # PnP inliers for the registration to be trusted
REFINEMENTS = 2
VISIBILITY_TOLERANCE = 0.02  # m, a point this far behind the nearest one is still seen


class SampleError(SourceError):
    """A sample file that cannot be imported; the message names the file and the problem."""

    def __init__(self, path: Path, problem: str):
        super().__init__(f"{path}: {problem}")
        self.path = path


class Samples:
    """The scenes of the samples under `folder` (iterated: layout (a) by stamp, then (b) and
    (c) by name), in one map: `map_name`, default `rgbd/<folder name>`. A sample is found by
    its `rgb_<stamp>.png` or its cloud; a missing partner file is an error, and so is a folder
    with no sample at all. `time` (ns): the time of the first sample that records none.
    `times`: how the times of the scenes read so far were found -> how many."""

    def __init__(self, folder: Path, robot: str = "pr2", map_name: str | None = None,
                 time: int | None = None):
        self.folder, self.robot, self.time = Path(folder), robot, time
        self.map_name = map_name or f"rgbd/{self.folder.name}"
        self.stamped = [(rgb, match.group(1)) for rgb in sorted(self.folder.rglob("rgb_*.png"))
                        if (match := re.fullmatch(r"rgb_(\d+)\.png", rgb.name))]
        self.clouds = _numbered(self.folder, "cloud")
        self.tests = _numbered(self.folder, "test_point_cloud_")
        if not (self.stamped or self.clouds or self.tests):
            raise SourceError(f"no RGB-D samples in {self.folder}: looked for "
                              + ", ".join(LAYOUTS))
        self.times: Counter[str] = Counter()

    def __iter__(self) -> Iterator[Scene]:
        return in_map(self._scenes(), self.map_name)

    def _scenes(self) -> Iterator[Scene]:
        for rgb, stamp in self.stamped:
            self.times[STAMPED] += 1
            yield _depth_scene(rgb, stamp, self.robot)
        for number, (cloud, n) in enumerate(self.clouds):
            if self.time is None:
                timestamp, how = cloud.stat().st_mtime_ns, FILE_TIMES
            else:
                timestamp, how = self.time + number * SECOND, GIVEN
            self.times[how] += 1
            yield _cloud_scene(cloud, _partner(cloud, f"image{n}.png"),
                               cloud.with_name(f"ground_truth{n}.lbl"), timestamp, self.robot)
        for cloud, n in self.tests:
            viewpoint = _read_viewpoint(_partner(cloud, f"test_viewpoint_{n}.vp"))
            self.times[VIEWPOINT_STAMPS] += 1
            yield _cloud_scene(cloud, _partner(cloud, f"test_rgb_image_{n}.png"), None,
                               viewpoint.stamp, self.robot)


def read_samples(folder: Path, robot: str = "pr2", map_name: str | None = None,
                 time: int | None = None) -> Samples:
    """The scenes of every sample under `folder` (see Samples)."""
    return Samples(folder, robot, map_name, time)


def _numbered(folder: Path, prefix: str) -> list[tuple[Path, str]]:
    """(path, n) of the `<prefix><n>.pcd` files under the folder, in natural order: cloud.pcd,
    cloud1.pcd, cloud2.pcd, ..., cloud10.pcd."""
    found = [(path, path.stem.removeprefix(prefix))
             for path in folder.rglob(f"{prefix}*.pcd")]
    return sorted(found, key=lambda f: (str(f[0].parent), int(f[1]) if f[1].isdigit() else -1,
                                        f[1]))


def camera_for(width: int, height: int, frame: str) -> CameraInfo:
    """The Kinect's intrinsics scaled to an image of this size (pixel centres stay centres)."""
    sx, sy = width / KINECT.width, height / KINECT.height
    fx, _, cx, _, fy, cy, *_ = KINECT.k
    return KINECT.model_copy(update={
        "width": width, "height": height, "frame": frame,
        "k": (fx * sx, 0.0, (cx + 0.5) * sx - 0.5, 0.0, fy * sy, (cy + 0.5) * sy - 0.5,
              0.0, 0.0, 1.0)})


def _matrix(camera: CameraInfo) -> np.ndarray:
    return np.array(camera.k).reshape(3, 3)


# --- layout (a): RGB + depth + viewpoint --------------------------------------------------------


def _depth_scene(rgb_path: Path, stamp: str, robot: str) -> Scene:
    depth_path = _partner(rgb_path, f"depth_{stamp}.png")
    pose = _read_viewpoint(_partner(rgb_path, f"viewpoint_{stamp}.vp"))
    rgb = _read_rgb(rgb_path)
    depth = cv2.imread(str(depth_path), cv2.IMREAD_UNCHANGED)
    if depth is None:
        raise SampleError(depth_path, "not a readable PNG")
    if depth.dtype != np.uint16 or depth.ndim != 2:
        raise SampleError(depth_path, "depth must be a 16-bit single-channel PNG (millimetres), "
                          f"got {depth.dtype.itemsize * 8}-bit with {_channels(depth)} channel(s)")
    if depth.shape != rgb.shape[:2]:
        raise SampleError(depth_path, f"depth is {depth.shape[1]}x{depth.shape[0]}, the RGB "
                          f"image {rgb.shape[1]}x{rgb.shape[0]}")
    log: list[LogLine] = []
    camera = camera_for(rgb.shape[1], rgb.shape[0], pose.child_frame)

    start = perf_counter()
    v, u = np.nonzero(depth)
    seen = camera.back_project(u, v, depth[v, u] / 1000.0)
    to_map = pose.matrix()
    points = seen @ to_map[:3, :3].T + to_map[:3, 3]
    plane = _fit_plane(points, viewer=to_map[:3, 3], up=np.array([0.0, 0.0, 1.0]))
    log.append(_line(start, f"plane fit on {min(len(points), PLANE_SAMPLE)} of {len(points)} "
                     "points: " + _describe(plane)))

    start = perf_counter()
    groups = _segment(points, plane)
    log.append(_line(start, f"Euclidean clustering ({CLUSTER_TOLERANCE * 100:.0f} cm, "
                     f"{VOXEL * 100:.0f} cm voxels): {len(groups)} object(s)"))

    start = perf_counter()
    pixels = np.stack([u, v], axis=1)
    clusters = [
        _cluster(rgb, pixels[g], points[g], plane, pose.frame, "counter_top",
                 PointCluster(points=PointCloud(points=points[g].astype(np.float32),
                                                frame=pose.frame)))
        for g in groups
    ]
    log.append(_line(start, f"{len(clusters)} cluster(s): crops, masks, hashes, histograms"))
    return Scene(
        timestamp=int(stamp),
        robot=robot,
        frame=pose.frame,
        camera_pose=pose,
        camera=camera,
        images={"color": Image(data=rgb, encoding="bgr8"),
                "depth": Image(data=depth, encoding="mono16")},
        clusters=clusters,
        log=log,
    )


VIEWPOINT_KEYS = {
    "translation": ("x", "y", "z"),
    "rotation": ("x", "y", "z", "w"),
    "frame": ("frame", "child_frame"),
    "viewpoint": ("stamp",),
}


def _read_viewpoint(path: Path) -> Transform:
    """The camera pose of a `.vp` file: INI sections [translation] x y z, [rotation] x y z w
    (a quaternion), [frame] frame child_frame, [viewpoint] stamp (seconds.nanoseconds)."""
    parser = configparser.ConfigParser()
    try:
        parser.read_string(path.read_text())
    except (configparser.Error, UnicodeDecodeError) as error:
        raise SampleError(path, f"not an INI viewpoint file ({error})") from None
    for section, keys in VIEWPOINT_KEYS.items():
        for key in keys:
            if not parser.has_option(section, key):
                raise SampleError(path, f"missing key {key!r} in section [{section}]")
    try:
        translation = tuple(float(parser["translation"][k]) for k in "xyz")
        rotation = tuple(float(parser["rotation"][k]) for k in "xyzw")
        seconds, _, fraction = parser["viewpoint"]["stamp"].strip().partition(".")
        stamp = int(seconds) * 10**9 + int(fraction.ljust(9, "0")[:9] or 0)
        return Transform(translation=translation, rotation=rotation,
                         frame=parser["frame"]["frame"],
                         child_frame=parser["frame"]["child_frame"], stamp=stamp)
    except ValidationError as error:  # (a ValueError: pydantic's text is lines and a link)
        raise SampleError(path, f"bad value: {problems_line(error)}") from None
    except ValueError as error:
        raise SampleError(path, f"bad value: {error}") from None


# --- layout (b): RGB + PCD (+ ground truth) -----------------------------------------------------


def _cloud_scene(cloud_path: Path, image_path: Path, labels_path: Path | None,
                 timestamp: int, robot: str) -> Scene:
    """The scene of a cloud and its image (layouts b and c), its objects the ground-truth
    segments when the labels file exists."""
    rgb = _read_rgb(image_path)
    cloud, viewpoint = read_pcd(cloud_path)
    log: list[LogLine] = []
    camera = camera_for(rgb.shape[1], rgb.shape[0], "camera")
    k = _matrix(camera)
    finite = np.nonzero(np.isfinite(PointCloud(points=cloud).xyz()).all(axis=1))[0]
    xyz = PointCloud(points=cloud[finite]).xyz()

    start = perf_counter()
    to_camera = np.linalg.inv(viewpoint)
    registered = _register(xyz, _colours(cloud[finite]), rgb, to_camera, k)
    if registered is None:
        log.append(_line(start, "could not register the cloud to the image; boxes assume the "
                         "PCD's VIEWPOINT", level="warning"))
    else:
        to_camera, inliers = registered
        angle = np.degrees(Rotation.from_matrix(to_camera[:3, :3]).magnitude())
        log.append(_line(start, f"registered the cloud to the image: {inliers} PnP inliers, "
                         f"camera rotated {angle:.1f} deg from the cloud frame"))
    camera_pose = np.linalg.inv(to_camera)

    if labels_path is not None and labels_path.exists():
        start = perf_counter()
        segments = _read_labels(labels_path, len(cloud))
        background = _background(segments, cloud)
        plane = None
        groups = [s for i, s in enumerate(segments) if i != background]
        log.append(_line(start, f"{len(segments)} ground-truth segment(s) from "
                         f"{labels_path.name}; " + ("none is the table" if background is None
                                                    else f"segment {background} is the table")))
    else:
        start = perf_counter()
        plane = _fit_plane(xyz, viewer=camera_pose[:3, 3])
        log.append(_line(start, "plane fit: " + _describe(plane)))
        start = perf_counter()
        groups = [finite[g] for g in _segment(xyz, plane)]
        log.append(_line(start, f"Euclidean clustering: {len(groups)} object(s)"))

    start = perf_counter()
    full = PointCloud(points=cloud).xyz()
    usable = np.full(len(cloud), False)
    usable[finite] = True
    groups = [g[usable[g]] for g in groups if usable[g].any()]  # NaN points have no place
    seen = np.full(len(cloud), False)
    seen[finite] = _visible(xyz, to_camera, k, rgb.shape[:2])
    pixels = np.zeros((len(cloud), 2), int)
    pixels[finite] = _project(xyz, to_camera, k)
    clusters = [
        _cluster(rgb, pixels[g[seen[g]]], full[g], plane, "cloud", "table",
                 PointCluster(indices=g.astype(np.int32), cloud="cloud"))
        for g in groups
    ]
    log.append(_line(start, f"{len(clusters)} cluster(s): crops, masks, hashes, histograms"))
    return Scene(
        timestamp=timestamp,
        robot=robot,
        frame="cloud",
        camera_pose=Transform(
            translation=tuple(camera_pose[:3, 3]),
            rotation=tuple(Rotation.from_matrix(camera_pose[:3, :3]).as_quat()),
            frame="cloud", child_frame="camera"),
        camera=camera,
        images={"color": Image(data=rgb, encoding="bgr8")},
        clouds={"cloud": PointCloud(points=cloud, frame="cloud")},
        clusters=clusters,
        log=log,
    )


PCD_TYPES = {"F": "f", "I": "i", "U": "u"}


def read_pcd(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """A PCD v0.7 file (DATA ascii or binary) as a structured array with the file's fields
    (PCL's "_" padding dropped; organised clouds flattened row by row), and its VIEWPOINT as
    the 4x4 pose of the sensor in the cloud's frame."""
    raw = path.read_bytes()
    header: dict[str, list[str]] = {}
    offset = 0
    while "DATA" not in header:
        end = raw.find(b"\n", offset)
        if end < 0:
            raise SampleError(path, "not a PCD file: the header has no DATA line")
        line = raw[offset:end].decode("ascii", "replace").strip()
        offset = end + 1
        if line and not line.startswith("#"):
            key, *values = line.split()
            header[key.upper()] = values
    missing = [key for key in ("FIELDS", "SIZE", "TYPE", "POINTS") if not header.get(key)]
    if missing or not header["DATA"]:
        raise SampleError(path, f"bad PCD header: no {' '.join(missing or ['DATA'])} values")
    try:
        names, sizes, kinds = header["FIELDS"], header["SIZE"], header["TYPE"]
        counts = [int(c) for c in header.get("COUNT", ["1"] * len(names))]
        points = int(header["POINTS"][0])
        viewpoint = [float(v) for v in header.get("VIEWPOINT", ["0"] * 3 + ["1"] + ["0"] * 3)]
        columns = [n if n != "_" else f"_padding{i}" for i, n in enumerate(names)]
        fields = [(n, f"<{PCD_TYPES[t]}{s}", (c,) if c > 1 else ())
                  for n, s, t, c in zip(columns, sizes, kinds, counts, strict=True)]
        dtype = np.dtype(fields)
    except (KeyError, IndexError, ValueError, TypeError) as error:
        raise SampleError(path, f"bad PCD header ({error!r})") from None
    if len(viewpoint) != 7:
        raise SampleError(path, "VIEWPOINT needs 7 numbers: tx ty tz qw qx qy qz")
    data = header["DATA"][0].lower()
    if data == "binary":  # PCL pads binary files to whole pages: more bytes are fine
        if len(raw) - offset < points * dtype.itemsize:
            raise SampleError(path, f"truncated: {points} points of {dtype.itemsize} bytes need "
                              f"{points * dtype.itemsize} bytes of data, the file has "
                              f"{len(raw) - offset}")
        cloud = np.frombuffer(raw, dtype, points, offset).copy()
    elif data == "ascii":
        rows = raw[offset:].decode("ascii", "replace").split("\n")
        values = [row.split() for row in rows if row.strip()]
        if len(values) < points:
            raise SampleError(path, f"truncated: {points} points announced, {len(values)} found")
        try:
            table = np.array(values[:points], dtype=float)
        except ValueError:
            raise SampleError(path, "ascii DATA rows must all hold the same numbers") from None
        if table.shape[1:] != (sum(counts),):
            raise SampleError(path, f"ascii rows hold {table.shape[1]} values, "
                              f"FIELDS/COUNT say {sum(counts)}")
        cloud = np.empty(points, dtype)
        column = 0
        for name, count in zip(columns, counts, strict=True):
            part = table[:, column:column + count]
            cloud[name] = part[:, 0] if count == 1 else part
            column += count
    else:
        raise SampleError(path, f"DATA {data} is not supported (only ascii and binary); "
                          "convert it with `pcl_convert_pcd_ascii_binary in.pcd out.pcd 1`")
    if not {"x", "y", "z"} <= set(names):
        raise SampleError(path, f"a cloud needs fields x, y, z; has {' '.join(names)}")
    pose = Pose(translation=viewpoint[:3], rotation=(*viewpoint[4:], viewpoint[3])).matrix()
    if "_" in names:
        cloud = repack_fields(cloud[[n for n in names if n != "_"]])
    return cloud, pose


def _read_labels(path: Path, size: int) -> list[np.ndarray]:
    """The segments of a `.lbl` file, in file order: "N segments", then per segment a dashed
    line, its number, a dashed line and its point indices, one per line."""
    lines = path.read_text().splitlines()
    match = re.fullmatch(r"\s*(\d+)\s+segments?\s*", lines[0] if lines else "")
    if not match:
        raise SampleError(path, "the first line must be '<N> segments'")
    segments: list[list[int]] = []
    number = 1
    while number < len(lines):
        line = lines[number].strip()
        if line.startswith("---"):
            if (number + 2 >= len(lines) or not lines[number + 1].strip().isdigit()
                    or not lines[number + 2].strip().startswith("---")):
                raise SampleError(path, f"line {number + 1}: a segment header is a dashed "
                                  "line, the segment number and another dashed line")
            segments.append([])
            number += 3
            continue
        if line:
            if not segments or not line.isdigit():
                raise SampleError(path, f"line {number + 1}: expected a point index, got "
                                  f"{line[:20]!r}")
            segments[-1].append(int(line))
        number += 1
    if len(segments) != int(match.group(1)):
        raise SampleError(path, f"announces {match.group(1)} segments, holds {len(segments)}")
    arrays = [np.array(s, dtype=np.int64) for s in segments]
    for i, indices in enumerate(arrays):
        if len(indices) and indices.max() >= size:
            raise SampleError(path, f"segment {i} has point index {indices.max()}, the cloud "
                              f"has {size} points")
    return arrays


def _background(segments: list[np.ndarray], cloud: np.ndarray) -> int | None:
    """The segment that is the table: the largest one, if it is a plane (90% of its points
    within 1.5 cm of one). low_noise's clouds are cut to the objects, so none is."""
    if not segments:
        return None
    largest = max(range(len(segments)), key=lambda i: len(segments[i]))
    points = PointCloud(points=cloud[segments[largest]]).xyz()
    points = points[np.isfinite(points).all(axis=1)]
    fit = _ransac(points, None, BACKGROUND_PLANARITY) if len(points) >= 3 else None
    return largest if fit is not None else None


# --- geometry ------------------------------------------------------------------------------------


def _ransac(points: np.ndarray, up: np.ndarray | None, share: float):
    """The plane (unit normal, offset) with most points within PLANE_TOLERANCE, refined by
    least squares on them, or None when it holds less than `share` of the points. Seeded, so
    the same points give the same plane. `up` limits the normal to MAX_TILT from it."""
    rng = np.random.default_rng(0)
    sample = points[rng.choice(len(points), min(len(points), PLANE_SAMPLE), replace=False)]
    a, b, c = (sample[rng.integers(0, len(sample), PLANE_ITERATIONS)] for _ in range(3))
    normals = np.cross(b - a, c - a)
    lengths = np.linalg.norm(normals, axis=1)
    usable = lengths > 1e-12
    normals[usable] /= lengths[usable, None]
    if up is not None:
        usable &= np.abs(normals @ up) >= np.cos(np.radians(MAX_TILT))
    if not usable.any():
        return None
    normals, a = normals[usable], a[usable]
    near = np.abs(sample @ normals.T - (normals * a).sum(axis=1)) < PLANE_TOLERANCE
    best = int(near.sum(axis=0).argmax())
    if near[:, best].sum() < share * len(sample):
        return None
    inliers = sample[near[:, best]]
    centre = inliers.mean(axis=0)
    normal = np.linalg.svd(inliers - centre, full_matrices=False)[2][2]
    return normal, -normal @ centre


def _fit_plane(points: np.ndarray, viewer: np.ndarray, up: np.ndarray | None = None):
    """The supporting surface, its normal pointing to the camera's side (objects stand on the
    side the camera looks from), or None when no plane holds MIN_PLANE_SHARE of the points.
    `up`: the surface is horizontal, its normal within MAX_TILT of `up`."""
    share = MIN_PLANE_SHARE["any" if up is None else "horizontal"]
    plane = _ransac(points, up, share) if len(points) >= 3 else None
    if plane is None:
        return None
    normal, offset = plane
    return (normal, offset) if normal @ viewer + offset >= 0 else (-normal, -offset)


def _describe(plane) -> str:
    if plane is None:
        return "no supporting plane, clustering all points"
    normal, offset = plane
    return f"normal ({normal[0]:.3f}, {normal[1]:.3f}, {normal[2]:.3f}), offset {offset:.3f} m"


def _segment(points: np.ndarray, plane) -> list[np.ndarray]:
    """Index arrays of the objects, largest first: the points in HEIGHT_BAND above the plane
    and inside its outline, Euclidean-clustered on a voxel grid, neither tiny nor huge. With no
    plane the cloud is taken to be cut to the objects already: all points, none too big."""
    if plane is None:
        candidates = np.arange(len(points))
    else:
        normal, offset = plane
        height = points @ normal + offset
        axis = np.linalg.svd(normal[None])[2][1:]  # two directions in the plane
        surface = (points[np.abs(height) < PLANE_TOLERANCE] @ axis.T)[::10]
        inside = np.full(len(points), True)
        try:
            edges = ConvexHull(surface).equations  # a x + b y + c <= 0 inside, (a, b) unit
            inside = (points @ axis.T @ edges[:, :2].T + edges[:, 2] < -HULL_MARGIN).all(axis=1)
        except (QhullError, ValueError):
            pass  # too few surface points for an outline: the height band alone decides
        candidates = np.nonzero((height > HEIGHT_BAND[0]) & (height < HEIGHT_BAND[1])
                                & inside)[0]
    if len(candidates) == 0:
        return []
    cells = np.floor(points[candidates] / VOXEL).astype(np.int64)
    _, first, cell_of = np.unique(cells, axis=0, return_index=True, return_inverse=True)
    centres = points[candidates[first]]
    pairs = cKDTree(centres).query_pairs(CLUSTER_TOLERANCE, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])),
                       shape=(len(centres), len(centres)))
    _, voxel_label = connected_components(graph, directed=False)
    sizes = np.bincount(voxel_label)
    label = voxel_label[cell_of.ravel()]
    groups = []
    for chosen in np.argsort(-sizes, kind="stable"):
        if sizes[chosen] < MIN_CLUSTER_VOXELS:
            break
        members = candidates[label == chosen]
        if plane is None or np.ptp(points[members], axis=0).max() <= MAX_CLUSTER_EXTENT:
            groups.append(members)
    return groups


def _project(points: np.ndarray, to_camera: np.ndarray, k: np.ndarray) -> np.ndarray:
    """Integer pixel (u, v) of each point, seen by a camera with intrinsics `k` at `to_camera`
    (4x4)."""
    camera = points @ to_camera[:3, :3].T + to_camera[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = camera @ k.T
        uv = uv[:, :2] / uv[:, 2:]
    return np.nan_to_num(np.round(uv), nan=-1, posinf=-1, neginf=-1).astype(int)


def _visible(points: np.ndarray, to_camera: np.ndarray, k: np.ndarray,
             shape: tuple[int, int]) -> np.ndarray:
    """Which points the camera sees: in the image, in front, and not behind other points. The
    depth buffer is min-filtered so that a surface whose points are sparser than the pixels
    still hides what is behind it."""
    depth = points @ to_camera[2, :3] + to_camera[2, 3]
    u, v = _project(points, to_camera, k).T
    inside = (depth > 0) & (u >= 0) & (u < shape[1]) & (v >= 0) & (v < shape[0])
    nearest = np.full(shape, np.inf, np.float32)
    np.minimum.at(nearest, (v[inside], u[inside]), depth[inside])
    nearest = cv2.erode(nearest, np.ones((3, 3), np.uint8))
    seen = np.full(len(points), False)
    seen[inside] = depth[inside] <= nearest[v[inside], u[inside]] + VISIBILITY_TOLERANCE
    return seen


def _colours(cloud: np.ndarray) -> np.ndarray:
    """BGR uint8 per point from PCL's packed `rgb`/`rgba` field (grey when there is none)."""
    colours = PointCloud(points=cloud).bgr()
    return np.full((len(cloud), 3), 128, np.uint8) if colours is None else colours


# --- registration of a cloud to its image -------------------------------------------------------


def _register(points: np.ndarray, colours: np.ndarray, image: np.ndarray,
              start: np.ndarray, k: np.ndarray) -> tuple[np.ndarray, int] | None:
    """The cloud-to-camera transform (4x4) that makes the cloud line up with the image, and
    its PnP inlier count; None when no view of the cloud matches the image. Views turned
    about the cloud's centre (up to 30 deg, smallest turn first) are rendered and matched to
    the image until one gives MIN_START_INLIERS; it is then refined by rendering again from
    the estimate."""
    sift = cv2.SIFT_create(nfeatures=4000)
    image_features = sift.detectAndCompute(image, None)
    if image_features[1] is None or len(points) < 10:
        return None
    centre = points.mean(axis=0) @ start[:3, :3].T + start[:3, 3]
    turns = sorted(itertools.product(START_ANGLES, START_ANGLES), key=lambda t: np.hypot(*t))
    for turn in turns:
        rotation = np.eye(4)
        rotation[:3, :3] = Rotation.from_euler("xy", turn, degrees=True).as_matrix()
        rotation[:3, 3] = centre - rotation[:3, :3] @ centre
        found = _match(points, colours, image_features, sift, rotation @ start, k,
                       image.shape[:2])
        if found is None or found[1] < MIN_START_INLIERS:
            continue
        for _ in range(REFINEMENTS):
            better = _match(points, colours, image_features, sift, found[0], k, image.shape[:2])
            if better is None or better[1] < found[1]:
                break
            found = better
        if found[1] >= MIN_INLIERS:
            return found
    return None


def _match(points, colours, image_features, sift, pose, k,
           shape: tuple[int, int]) -> tuple[np.ndarray, int] | None:
    """Render the coloured cloud from `pose` at the image's size (`shape`), match SIFT
    features of the rendering to the image, and solve PnP on the 3D points under the matched
    features."""
    height, width = shape
    depth = points @ pose[2, :3] + pose[2, 3]
    u, v = _project(points, pose, k).T
    order = np.argsort(-depth)  # far to near: the nearest point wins its pixel
    order = order[(depth[order] > 0) & (u[order] >= 0) & (u[order] < width)
                  & (v[order] >= 0) & (v[order] < height)]
    rendering = np.zeros((height, width, 3), np.uint8)
    index = np.full((height, width), -1)
    rendering[v[order], u[order]] = colours[order]
    index[v[order], u[order]] = order
    drawn = (index >= 0).astype(np.uint8)
    covered = cv2.morphologyEx(drawn, cv2.MORPH_CLOSE, np.ones((5, 5), np.uint8))
    rendering = cv2.inpaint(rendering, covered - drawn, 2, cv2.INPAINT_TELEA)
    keys, descriptors = sift.detectAndCompute(rendering, covered * 255)
    image_keys, image_descriptors = image_features
    if descriptors is None or len(descriptors) < 2:
        return None
    objects, pixels = [], []
    for pair in cv2.BFMatcher().knnMatch(descriptors, image_descriptors, k=2):
        if len(pair) < 2 or pair[0].distance >= 0.8 * pair[1].distance:
            continue
        x, y = (int(round(c)) for c in keys[pair[0].queryIdx].pt)
        near = index[max(0, y - 2):y + 3, max(0, x - 2):x + 3]
        near = near[near >= 0]
        if len(near):
            objects.append(points[near[np.argmin(depth[near])]])
            pixels.append(image_keys[pair[0].trainIdx].pt)
    if len(objects) < 6:
        return None
    ok, rvec, tvec, inliers = cv2.solvePnPRansac(
        np.array(objects), np.array(pixels), k, None, iterationsCount=1000,
        reprojectionError=5.0, flags=cv2.SOLVEPNP_AP3P)
    if not ok or inliers is None:
        return None
    chosen = inliers.ravel()
    rvec, tvec = cv2.solvePnPRefineLM(np.array(objects)[chosen], np.array(pixels)[chosen], k,
                                      None, rvec, tvec)
    found = np.eye(4)
    found[:3, :3] = cv2.Rodrigues(rvec)[0]
    found[:3, 3] = tvec.ravel()
    return found, len(inliers)


# --- clusters ------------------------------------------------------------------------------------


def _cluster(image: np.ndarray, pixels: np.ndarray, points: np.ndarray, plane, frame: str,
             region: str, hypothesis: PointCluster) -> Cluster:
    """A Cluster of an object's points: where it is, how big, and what it looks like where
    the camera sees it (`pixels`: its visible points' pixels; none, no ImageROI)."""
    centroid = tuple(float(c) for c in points.mean(axis=0))
    low, high = points.min(axis=0), points.max(axis=0)
    annotations = [
        Location(source=SOURCE, region=region, position=centroid, frame=frame, relation="on"),
        Geometry(source=SOURCE, size=tuple(float(s) for s in high - low),
                 pose=Pose(translation=tuple(float(c) for c in (low + high) / 2), frame=frame),
                 distance_to_plane=None if plane is None
                 else float((points @ plane[0] + plane[1]).min())),
    ]
    hypotheses: list = [hypothesis]
    if len(pixels):
        mask = np.zeros(image.shape[:2], np.uint8)
        mask[pixels[:, 1], pixels[:, 0]] = 255
        mask = cv2.morphologyEx(mask, cv2.MORPH_CLOSE, np.ones((5, 5), np.uint8))
        mask = cv2.dilate(mask, np.ones((3, 3), np.uint8))
        x, y, w, h = cv2.boundingRect(mask)
        crop = image[y:y + h, x:x + w].copy()
        mask = mask[y:y + h, x:x + w].copy()
        phash = str(imagehash.phash(PILImage.fromarray(cv2.cvtColor(crop, cv2.COLOR_BGR2RGB))))
        hsv = cv2.cvtColor(crop, cv2.COLOR_BGR2HSV)
        histogram = cv2.calcHist([hsv], [0, 1], mask, [16, 16], [0, 180, 0, 256])
        histogram = (histogram / max(float(histogram.sum()), 1.0)).astype(np.float32)
        hypotheses.insert(0, ImageROI(box=(x, y, w, h), image="color", phash=phash,
                                      mask=Image(data=mask, encoding="mono8"),
                                      crop=Image(data=crop, encoding="bgr8")))
        annotations.append(ColorHistogram(source=SOURCE, histogram=histogram, space="HS"))
    return Cluster(hypotheses=hypotheses, annotations=annotations)


# --- files ---------------------------------------------------------------------------------------


def _partner(path: Path, name: str) -> Path:
    partner = path.with_name(name)
    if not partner.exists():
        raise SampleError(path, f"has no {name} next to it")
    return partner


def _read_rgb(path: Path) -> np.ndarray:
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise SampleError(path, "not a readable PNG")
    if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] not in (3, 4):
        raise SampleError(path, "the colour image must be 8-bit RGB, got "
                          f"{image.dtype.itemsize * 8}-bit with {_channels(image)} channel(s)")
    return np.ascontiguousarray(image[:, :, :3])


def _channels(image: np.ndarray) -> int:
    return 1 if image.ndim == 2 else image.shape[2]


def _line(start: float, message: str, level: str = "info") -> LogLine:
    return LogLine(source=SOURCE, message=message, level=level,
                   duration_ms=(perf_counter() - start) * 1000)
