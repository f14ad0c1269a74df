"""Import RoboSherlock's MongoDB storage, from a `mongodump` folder or a live database.

RoboSherlock wrote one `cas` document per frame: `_timestamp` (int64 ns) and, per view, the id
of a document in the collection of that name (`scene`, `camera_info`, `color_image_hd`, ...).
Every frame becomes one Scene of the given robot, at that timestamp:

- `scene` (rs.core.Scene): `viewPoint` -> camera_pose (its frame -> Scene.frame), the clusters
  among `identifiables` -> clusters, `annotations` -> scene annotations;
- `camera_info` -> camera; views holding an rs.cv.Mat -> images, named without "_image"
  (`color_image_hd` -> "color_hd"); any other view (`camera_info_hd`: a Scene has one set of
  intrinsics) is kept whole as an Unknown scene annotation.

A cluster (rs.scene.Cluster, MergedCluster, Object) becomes a Cluster: `rois` -> an ImageROI of
"color" (roi, mask) and one of "color_hd" (roi_hires, mask_hires); `points` (ReferenceClusterPoints)
-> PointCluster(indices); its annotations one by one; the rest of its document (RoboSherlock's
id, and for an Object `clusters`, `lastSeen`, `wasSeen`, `inView`, `disappeared`) is kept as an
Unknown annotation of its rs type, so the RoboSherlock ids survive.

`persistent_objects` (PnP09) is RoboSherlock's belief state: one rs.scene.Object per physical
object, its annotations merged over every frame it was seen in, `clusters` naming the per-frame
clusters it was matched with. Those per-frame clusters lived in `scene` documents the dump does
not contain, so the object is imported once, as a Cluster of the frame it was last seen in
(`lastSeen` is a frame's timestamp; the closest frame otherwise): the observation its merged
annotations describe, with nothing duplicated across frames. Identity over time is left to
percept-memory's own consolidation; RoboSherlock's object id and cluster ids stay in the kept
rs.scene.Object annotation.

Annotations: Classification, Detection, Shape, SemanticColor (color + ratio -> ratios),
ColorHistogram (hist Mat), GroundTruth (classificationGT.classname, pose) map onto ours;
Geometry (boundingBox, world pose, distanceToPlane, size) and SemanticSize (size) -> Geometry;
PoseAnnotation (world pose) -> Location; PclFeature (feat_type, float32 feature) and Features
(descriptors Mat, named by its source) -> FeatureVector. Each keeps RoboSherlock's `source` and
its `_id` as the annotation id, so importing again yields the same ids. Deliberately not kept:
the camera-frame copies of the Geometry/PoseAnnotation pose (the world pose is what the memory
queries), SemanticSize's confidence, Features' descriptorType (the vector's dtype says it), and
of camera_info only the intrinsics our CameraInfo holds (not p, r, binning, roi).
Any other type (Segment with its rs.cv.Moments, ...), or a document with content in a field our
type cannot hold (a Classification's model, a Features' response), is kept whole as `Unknown`:
no document and no type is dropped.

Format conventions: `_parent` ids, int64 ns timestamps, primitive arrays of 20 or more elements
as raw little-endian bytes (shorter ones as arrays), null references as `{}`; rs.cv.Mat is
rows x cols of OpenCV type `mat_type` in continuous row-major bytes. A malformed document raises
RoboSherlockFormatError naming the collection, the document `_id` and the field.
"""

from __future__ import annotations

import bisect
import logging
import re
from collections.abc import Callable, Iterable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import bson
import numpy as np
from bson.errors import InvalidBSON
from pydantic import ValidationError
from pymongo import MongoClient
from pymongo.errors import PyMongoError

from percept_memory.converters import TYPE_KEY, Unknown, decode
from percept_memory.ingest.errors import SourceError
from percept_memory.ingest.service import in_map
from percept_memory.memory.errors import reason, redacted
from percept_memory.memory.types import (
    CameraInfo,
    Classification,
    Cluster,
    ColorHistogram,
    Detection,
    FeatureVector,
    Geometry,
    GroundTruth,
    Image,
    ImageROI,
    Location,
    PointCluster,
    Pose,
    Scene,
    SemanticColor,
    Shape,
    Transform,
)

log = logging.getLogger(__name__)

CAS = "cas"
SCENE_VIEW = "scene"
CAMERA_VIEW = "camera_info"
PERSISTENT_OBJECTS = "persistent_objects"
CLUSTER_TYPES = frozenset({"rs.scene.Cluster", "rs.scene.MergedCluster", "rs.scene.Object"})
MAT = "rs.cv.Mat"
LFS_POINTER = b"version https://git-lfs.github.com/spec/"

# OpenCV depth codes (mat_type & 7) as little-endian numpy dtypes: CV_8U, 8S, 16U, 16S, 32S,
# 32F, 64F, 16F.
CV_DEPTHS = ("<u1", "<i1", "<u2", "<i2", "<i4", "<f4", "<f8", "<f2")
NAMED_ENCODINGS = {("u1", 1): "mono8", ("u1", 3): "bgr8", ("u1", 4): "bgra8"}
PHASH = re.compile("[0-9a-f]{16}")


class RoboSherlockFormatError(SourceError):
    """A RoboSherlock document that does not say what the format says it should."""

    def __init__(self, collection: str, doc_id: Any, field: str, problem: str):
        self.collection, self.doc_id, self.field, self.problem = collection, doc_id, field, problem
        super().__init__(
            f"RoboSherlock {collection} document {doc_id}: field {field or '(document)'}: "
            f"{problem}"
        )


# --- ways in ------------------------------------------------------------------------------


def read_dump(folder: Path, robot: str = "pr2", map_name: str | None = None
              ) -> Iterator[Scene]:
    """The frames of a `mongodump` folder of RoboSherlock's storage, oldest first, in one map
    (`map_name`, default `robosherlock/<folder name>`)."""
    folder = Path(folder)
    if not (folder / f"{CAS}.bson").is_file():
        raise SourceError(
            f"{folder} holds no {CAS}.bson: not a mongodump folder of a RoboSherlock database"
        )
    files = [path for path in sorted(folder.glob("*.bson"))
             if not path.name.startswith("system.")]
    pointers = [path for path in files if _is_lfs_pointer(path)]
    if pointers:
        log.warning("%s: skipping %s: git-lfs pointers, never fetched (`git lfs pull`)",
                    folder.name, ", ".join(path.name for path in pointers))
    collections = {path.stem: _dump_documents(path) for path in files if path not in pointers}
    return in_map(read_collections(collections, robot), map_name or f"robosherlock/{folder.name}")


def read_database(uri: str, db: str, robot: str = "pr2", map_name: str | None = None,
                  timeout_ms: int = 5000) -> Iterator[Scene]:
    """The frames of a live RoboSherlock database, oldest first, in one map (`map_name`,
    default `robosherlock/<db>`). A server that does not answer within `timeout_ms` is a
    SourceError."""
    with MongoClient(uri, serverSelectionTimeoutMS=timeout_ms) as client:
        database = client[db]
        try:
            names = [n for n in database.list_collection_names() if not n.startswith("system.")]
        except PyMongoError as error:
            raise SourceError(f"cannot read the RoboSherlock database at {redacted(uri)}: "
                              f"{reason(error)}") from None
        yield from in_map(read_collections({name: database[name].find() for name in names},
                                           robot), map_name or f"robosherlock/{db}")


def read_collections(
    collections: Mapping[str, Iterable[Mapping]], robot: str = "pr2"
) -> Iterator[Scene]:
    """The frames of RoboSherlock's collections (name -> its documents), oldest first."""
    if CAS not in collections:
        raise SourceError(f"no {CAS!r} collection: this is not a RoboSherlock database")
    frames = sorted(((_frame_time(doc), doc) for doc in collections[CAS]), key=lambda f: f[0])
    by_id = {name: _by_id(name, docs) for name, docs in collections.items() if name != CAS}
    objects = _place_objects(by_id.pop(PERSISTENT_OBJECTS, {}), [t for t, _ in frames])
    _report_unreferenced(by_id, [doc for _, doc in frames])
    for time, frame in frames:
        yield _scene(time, frame, by_id, objects.get(time, []), robot)


def _is_lfs_pointer(path: Path) -> bool:
    """A file git-lfs stands in for, the data itself never fetched."""
    with path.open("rb") as file:
        return file.read(len(LFS_POINTER)) == LFS_POINTER


def _dump_documents(path: Path) -> Iterator[dict]:
    with path.open("rb") as file:
        try:
            yield from bson.decode_file_iter(file)
        except InvalidBSON as error:
            raise SourceError(f"{path} is not a mongodump BSON file: {error}") from None


# --- errors that name the collection, the document and the field -----------------------------


class _Bad(Exception):
    def __init__(self, path: list, problem: str):
        self.path, self.problem = path, problem


@contextmanager
def _at(*path):
    """Problems inside are about the field at `path` (relative to the enclosing _at)."""
    try:
        yield
    except RoboSherlockFormatError:
        raise
    except _Bad as bad:
        bad.path[:0] = path
        raise
    except KeyError as error:
        raise _Bad([*path, error.args[0]], "missing") from None
    except ValidationError as error:
        problems = error.errors(include_url=False, include_input=False)
        message = "; ".join(f"{'.'.join(map(str, e['loc']))}: {e['msg']}" for e in problems)
        raise _Bad(list(path), message) from None
    except (TypeError, ValueError, IndexError, AttributeError, OverflowError) as error:
        raise _Bad(list(path), str(error)) from None


@contextmanager
def _reading(collection: str, doc: Mapping):
    try:
        with _at():
            yield
    except _Bad as bad:
        field = ".".join(map(str, bad.path))
        raise RoboSherlockFormatError(collection, doc.get("_id"), field, bad.problem) from None


def _frame_time(doc: Mapping) -> int:
    with _reading(CAS, doc), _at("_timestamp"):
        time = doc["_timestamp"]
        if not isinstance(time, int) or isinstance(time, bool) or time < 0:
            raise ValueError(f"expected int64 nanoseconds since the epoch, got {time!r}")
        return int(time)


def _by_id(collection: str, docs: Iterable[Mapping]) -> dict:
    index = {}
    for doc in docs:
        with _reading(collection, doc):
            index[doc["_id"]] = doc
    return index


def _report_unreferenced(by_id: dict[str, dict], frames: list[Mapping]) -> None:
    referenced = {view for frame in frames for view in frame}
    for name in sorted(by_id.keys() - referenced):
        if by_id[name]:
            log.info("not imported: no frame refers to collection %s (%d documents)",
                     name, len(by_id[name]))


# --- frames -------------------------------------------------------------------------------


def _scene(
    time: int, frame: Mapping, by_id: dict[str, dict], objects: list[Cluster], robot: str
) -> Scene:
    parts: dict[str, Any] = {"images": {}, "clusters": [], "annotations": []}
    for view, ref in frame.items():
        with _reading(CAS, frame), _at(view):
            doc = by_id.get(view, {}).get(ref) if view not in ("_id", "_timestamp") else None
        if doc is None:  # not a view, or its document is not in this store
            continue
        with _reading(view, doc):
            if view == SCENE_VIEW:
                _scene_view(doc, parts)
            elif view == CAMERA_VIEW:
                parts["camera"] = _camera(doc)
            elif doc.get(TYPE_KEY) == MAT:
                parts["images"][view.replace("_image", "")] = _image(doc)
            else:
                parts["annotations"].append(_kept(doc))
    parts["clusters"].extend(objects)
    with _reading(CAS, frame):
        return Scene(timestamp=time, robot=robot, **parts)


def _scene_view(doc: Mapping, parts: dict) -> None:
    viewpoint = _ref(doc, "viewPoint")
    if viewpoint is not None:
        with _at("viewPoint"):
            parts["camera_pose"] = _transform(viewpoint)
        parts["frame"] = parts["camera_pose"].frame
    for index, item in enumerate(_list(doc, "identifiables")):
        with _at("identifiables", index):
            if item.get(TYPE_KEY) in CLUSTER_TYPES:
                parts["clusters"].append(_cluster(item))
            else:
                parts["annotations"].append(_kept(item))
    parts["annotations"].extend(_converted_list(doc, "annotations"))
    parts["annotations"].append(_kept(_without(doc, "viewPoint", "identifiables", "annotations")))


def _camera(doc: Mapping) -> CameraInfo:
    header = _ref(doc, "header") or {}
    return CameraInfo(
        width=doc["width"],
        height=doc["height"],
        k=_numbers(doc, "k", "<f8"),
        d=_numbers(doc, "d", "<f8") if "d" in doc else [],
        distortion_model=doc.get("distortion_model") or "plumb_bob",
        frame=header.get("frame_id", ""),
    )


# --- clusters and persistent objects ------------------------------------------------------


def _cluster(doc: Mapping) -> Cluster:
    hypotheses = [h for key in ("rois", "points") for h in _converted(doc, key)]
    annotations = _converted_list(doc, "annotations")
    annotations.append(_kept(_without(doc, "rois", "points", "annotations")))
    return Cluster(hypotheses=hypotheses, annotations=annotations)


def _place_objects(objects: dict, times: list[int]) -> dict[int, list[Cluster]]:
    """Frame timestamp -> the persistent objects last seen in that frame, as clusters."""
    placed: dict[int, list[Cluster]] = {}
    if objects and not times:
        log.warning("not imported: %d persistent objects, but no frame to place them in",
                    len(objects))
        return placed
    for doc in sorted(objects.values(), key=lambda d: str(d["_id"])):
        with _reading(PERSISTENT_OBJECTS, doc):
            with _at("lastSeen"):
                frame_time = _closest(times, doc["lastSeen"])
            placed.setdefault(frame_time, []).append(_cluster(doc))
    return placed


def _closest(times: list[int], time: int) -> int:
    index = bisect.bisect_left(times, time)
    return min(times[max(index - 1, 0) : index + 1], key=lambda t: abs(t - time))


# --- rs documents -> ours, or kept whole ----------------------------------------------------


@dataclass(frozen=True)
class _Rule:
    """How an rs type becomes ours: `build` maps a document onto our objects ([] when it cannot
    represent this one); `fields` are the rs fields it accounts for. A document with content in
    any other field is kept whole instead, so nothing is lost."""

    build: Callable[[Mapping], list]
    fields: frozenset[str]


_RULES: dict[str, _Rule] = {}
_BOOKKEEPING = frozenset({"_id", "_parent", TYPE_KEY, "source"})


def _maps(rs_type: str, *fields: str):
    def register(build: Callable[[Mapping], list]) -> Callable[[Mapping], list]:
        _RULES[rs_type] = _Rule(build, _BOOKKEEPING | set(fields))
        return build

    return register


def _converted(doc: Mapping, key: str) -> list:
    """Our objects for the rs document in `doc[key]` (none for a null reference)."""
    value = _ref(doc, key)
    if value is None:
        return []
    with _at(key):
        return _convert(value)


def _converted_list(doc: Mapping, key: str) -> list:
    """Our objects for the rs documents in the list `doc[key]`."""
    out = []
    for index, item in enumerate(_list(doc, key)):
        with _at(key, index):
            out.extend(_convert(item))
    return out


def _convert(doc: Mapping) -> list:
    rule = _RULES.get(doc.get(TYPE_KEY))
    if rule is not None and not any(
        key not in rule.fields and _has_content(value) for key, value in doc.items()
    ):
        built = rule.build(doc)
        if built:
            return built
    return [_kept(doc)]


def _kept(doc: Mapping) -> Unknown:
    """The document whole, as the generic codec keeps a type it does not know. (A name that is
    an alias of ours, like rs.tf.StampedPose, is kept the same way: the layout is not ours.)"""
    kept = decode(doc)
    if not isinstance(kept, Unknown):
        kept = Unknown.model_construct(type_name=doc[TYPE_KEY], fields=dict(doc))
    return kept


def _has_content(value: Any) -> bool:
    return not (value is None or value == {} or value == [] or value == "")


def _annotation(doc: Mapping) -> dict:
    return {"id": doc.get("_id"), "source": doc.get("source", "")}


@_maps("rs.annotation.Classification", "classname", "classifier", "featurename", "confidences")
def _classification(doc: Mapping) -> list:
    confidences = {}
    for index, item in enumerate(_list(doc, "confidences")):  # rs.annotation.ClassConfidence
        with _at("confidences", index):
            confidences[item["name"]] = item["score"]
    return [Classification(
        **_annotation(doc), class_name=doc["classname"], classifier=doc.get("classifier", ""),
        feature=doc.get("featurename", ""), confidences=confidences,
    )]


@_maps("rs.annotation.GroundTruth", "classificationGT", "pose")
def _ground_truth(doc: Mapping) -> list:
    truth = _ref(doc, "classificationGT")
    if truth is None:
        return []
    with _at("classificationGT"):
        class_name = truth["classname"]
    pose = _ref(doc, "pose")
    with _at("pose"):
        pose = None if pose is None else _pose(pose)
    return [GroundTruth(**_annotation(doc), class_name=class_name, pose=pose)]


@_maps("rs.annotation.Detection", "name", "confidence")
def _detection(doc: Mapping) -> list:
    return [Detection(**_annotation(doc), name=doc["name"], confidence=doc.get("confidence"))]


@_maps("rs.annotation.Shape", "shape", "confidence")
def _shape(doc: Mapping) -> list:
    return [Shape(**_annotation(doc), shape=doc["shape"], confidence=doc.get("confidence"))]


@_maps("rs.annotation.SemanticColor", "color", "ratio")
def _semantic_color(doc: Mapping) -> list:
    colors, ratios = _list(doc, "color"), _numbers(doc, "ratio", "<f4")
    if len(colors) != len(ratios):
        raise ValueError(f"{len(colors)} colours but {len(ratios)} ratios")
    return [SemanticColor(**_annotation(doc), ratios=dict(zip(colors, ratios, strict=True)))]


@_maps("rs.annotation.ColorHistogram", "hist")
def _color_histogram(doc: Mapping) -> list:
    with _at("hist"):
        return [ColorHistogram(**_annotation(doc), histogram=_mat(doc["hist"]))]


@_maps("rs.annotation.Geometry", "boundingBox", "world", "camera", "distanceToPlane", "size")
def _geometry(doc: Mapping) -> list:
    box, world = _ref(doc, "boundingBox"), _ref(doc, "world")
    with _at("boundingBox"):
        size = None if box is None else (box["width"], box["depth"], box["height"])
        volume = None if box is None else box.get("volume")
    with _at("world"):
        pose = None if world is None else _pose(world)
    return [Geometry(
        **_annotation(doc), size=size, volume=volume, pose=pose,
        distance_to_plane=doc.get("distanceToPlane"), semantic_size=doc.get("size") or None,
    )]


@_maps("rs.annotation.SemanticSize", "size", "confidence")
def _semantic_size(doc: Mapping) -> list:
    return [Geometry(**_annotation(doc), semantic_size=doc["size"])]


@_maps("rs.annotation.PoseAnnotation", "world", "camera")
def _pose_annotation(doc: Mapping) -> list:
    world = _ref(doc, "world")
    if world is None:  # only the camera-frame pose, which Location cannot hold
        return []
    with _at("world"):
        pose = _pose(world)
    return [Location(**_annotation(doc), position=pose.translation, frame=pose.frame, pose=pose)]


@_maps("rs.pcl.PclFeature", "feat_type", "feature")
def _pcl_feature(doc: Mapping) -> list:
    return [FeatureVector(
        **_annotation(doc), name=doc["feat_type"], vector=_array(doc, "feature", "<f4")
    )]


@_maps("rs.annotation.Features", "descriptors", "descriptorType")
def _features(doc: Mapping) -> list:
    with _at("descriptors"):
        vector = _mat(doc["descriptors"])
    return [FeatureVector(**_annotation(doc), name=doc.get("source", ""), vector=vector)]


@_maps("rs.cv.ImageROI", "roi", "mask", "roi_hires", "mask_hires", "phash")
def _rois(doc: Mapping) -> list:
    phash = doc.get("phash") or None
    if phash is not None and not PHASH.fullmatch(phash):
        return []  # a hash of another kind than our 64-bit pHash: kept as it is
    rois = []
    for roi, mask, image in (("roi", "mask", "color"), ("roi_hires", "mask_hires", "color_hd")):
        rect, pixels = _ref(doc, roi), _ref(doc, mask)
        if rect is None:
            if pixels is not None:
                return []  # a mask without its box: kept as it is
            continue
        with _at(roi):
            box = _rect(rect)
        with _at(mask):
            mask_image = None if pixels is None else _image(pixels)
        rois.append(ImageROI(box=box, image=image, mask=mask_image,
                             phash=phash if image == "color" else None))
    return rois


@_maps("rs.pcl.ReferenceClusterPoints", "indices")
def _reference_points(doc: Mapping) -> list:
    indices = _ref(doc, "indices")  # rs.pcl.PointIndices; its header says nothing
    if indices is None:
        return []
    with _at("indices"):
        return [PointCluster(indices=_array(indices, "indices", "<i4"))]


# --- values -------------------------------------------------------------------------------


def _ref(doc: Mapping, key: str) -> Mapping | None:
    """The document `doc[key]` refers to; None for a null reference (`{}`) or none at all."""
    value = doc.get(key)
    if value is None or value == {}:
        return None
    if not isinstance(value, Mapping):
        raise _Bad([key], f"expected a document, got {type(value).__name__}")
    return value


def _list(doc: Mapping, key: str) -> list:
    """The list `doc[key]`; empty for a null reference (`{}`) or none at all."""
    value = doc.get(key)
    if value is None or value == {}:
        return []
    if not isinstance(value, list):
        raise _Bad([key], f"expected an array, got {type(value).__name__}")
    return value


def _without(doc: Mapping, *keys: str) -> dict:
    return {k: v for k, v in doc.items() if k not in keys}


def _array(doc: Mapping, key: str, dtype: str) -> np.ndarray:
    """A primitive array: raw little-endian bytes from 20 elements on, a BSON array below."""
    with _at(key):
        value = doc[key]
        if isinstance(value, bytes):
            if len(value) % np.dtype(dtype).itemsize:
                raise ValueError(f"{len(value)} bytes is no whole number of {dtype} values")
            return np.frombuffer(value, dtype).copy()
        if isinstance(value, list):
            return np.asarray(value, dtype)
        raise TypeError(f"expected binary data or an array, got {type(value).__name__}")


def _numbers(doc: Mapping, key: str, dtype: str) -> list:
    """A primitive array as Python numbers (exact: the array's own element type)."""
    return _array(doc, key, dtype).tolist()


def _mat(doc: Mapping) -> np.ndarray:
    """An rs.cv.Mat as the numpy array OpenCV would have: rows x cols [x channels]."""
    rows, cols, mat_type = doc["rows"], doc["cols"], doc["mat_type"]
    with _at("mat_type"):
        if not 0 <= mat_type < 4096:  # 8 depths x up to 512 channels
            raise ValueError(f"{mat_type} is no OpenCV type code")
        dtype = np.dtype(CV_DEPTHS[mat_type & 7])
    channels = (mat_type >> 3) + 1
    shape = (rows, cols) if channels == 1 else (rows, cols, channels)
    data = _array(doc, "data", "<i1") if "data" in doc else np.empty(0, np.int8)  # empty Mat
    with _at("data"):
        expected = rows * cols * channels * dtype.itemsize
        if data.size != expected:
            raise ValueError(
                f"{data.size} bytes, but {rows} x {cols} of mat_type {mat_type} take {expected}"
            )
    return data.view(dtype).reshape(shape)


def _image(doc: Mapping) -> Image:
    pixels = _mat(doc)
    channels = pixels.shape[2] if pixels.ndim == 3 else 1
    code = pixels.dtype.str[1:]  # "u1", "f4", ...
    kind = {"u": "U", "i": "S", "f": "F"}[code[0]]
    encoding = NAMED_ENCODINGS.get((code, channels), f"{pixels.itemsize * 8}{kind}C{channels}")
    return Image(data=pixels, encoding=encoding)


def _rect(doc: Mapping) -> tuple[int, int, int, int]:
    """An rs.cv.Rect as x, y, width, height."""
    pos, size = doc["pos"], doc["size"]
    return pos["x"], pos["y"], size["width"], size["height"]


def _pose_fields(doc: Mapping) -> dict:
    """An rs.tf.StampedPose / StampedTransform: translation, rotation (a row-major 3x3 matrix in
    old logs, a quaternion x, y, z, w in newer ones), frame, int64 ns timestamp."""
    rotation = _numbers(doc, "rotation", "<f8")
    with _at("rotation"):
        rotation = _quaternion(rotation)
    return {"translation": _numbers(doc, "translation", "<f8"), "rotation": rotation,
            "frame": doc["frame"], "stamp": doc.get("timestamp")}


def _pose(doc: Mapping) -> Pose:
    return Pose(**_pose_fields(doc))


def _transform(doc: Mapping) -> Transform:
    return Transform(**_pose_fields(doc), child_frame=doc["childFrame"])


def _quaternion(rotation: list[float]) -> tuple[float, float, float, float]:
    """x, y, z, w of a rotation given as a quaternion or as a row-major 3x3 matrix."""
    if len(rotation) == 4:
        return tuple(rotation)
    if len(rotation) != 9:
        raise ValueError(f"{len(rotation)} numbers: expected 9 (3x3 matrix) or 4 (quaternion)")
    m = np.array(rotation).reshape(3, 3)
    if not np.allclose(m @ m.T, np.eye(3), atol=1e-4) or np.linalg.det(m) < 0:
        raise ValueError("the 3x3 matrix is not a rotation (not orthonormal, or a reflection)")
    # Shepperd's method: divide by the largest of 4w^2, 4x^2, 4y^2, 4z^2 for precision.
    trace = m[0, 0] + m[1, 1] + m[2, 2]
    if trace > 0:
        s = 2 * np.sqrt(trace + 1)
        q = ((m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, s / 4)
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2 * np.sqrt(1 + m[0, 0] - m[1, 1] - m[2, 2])
        q = (s / 4, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s)
    elif m[1, 1] > m[2, 2]:
        s = 2 * np.sqrt(1 + m[1, 1] - m[0, 0] - m[2, 2])
        q = ((m[0, 1] + m[1, 0]) / s, s / 4, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s)
    else:
        s = 2 * np.sqrt(1 + m[2, 2] - m[0, 0] - m[1, 1])
        q = ((m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, s / 4, (m[1, 0] - m[0, 1]) / s)
    return tuple(float(c) for c in q)

