"""The type system: every kind of thing percept-memory stores, each a registered pydantic model."""

from percept_memory.converters import Unknown

from .annotations import (
    Annotation,
    Barcode,
    Classification,
    ColorHistogram,
    Detection,
    FeatureVector,
    Geometry,
    GroundTruth,
    Location,
    LogLine,
    Logo,
    Product,
    Relation,
    SemanticColor,
    Shape,
    Text,
    Tracking,
    WebLookup,
)
from .base import (
    Id,
    Identifiable,
    Model,
    Timestamp,
    datetime_from_timestamp,
    is_timestamp,
    iso_from_timestamp,
    stored_type,
    timestamp_from_datetime,
    timestamp_from_iso,
)
from .curation import Correction, DifferentObject, Rejection, Relabel, SameObject, Undo
from .hypotheses import Hypothesis, ImageROI, PointCluster, SpatialVolume
from .raw import Box, CameraInfo, Image, NDArray, PointCloud, Pose, Quaternion, Transform, Vec3
from .scene import Cluster, Scene
from .visual_words import VisualWords

__all__ = [
    "Annotation", "Barcode", "Box", "CameraInfo", "Classification", "Cluster", "ColorHistogram",
    "Correction", "Detection", "DifferentObject", "FeatureVector", "Geometry", "GroundTruth",
    "Hypothesis", "Id", "Identifiable", "Image", "ImageROI", "Location", "LogLine", "Logo",
    "Model", "NDArray",
    "PointCloud", "PointCluster", "Pose", "Product", "Quaternion", "Rejection", "Relabel",
    "Relation", "SameObject", "Scene", "SemanticColor", "Shape", "SpatialVolume", "Text",
    "Timestamp", "Tracking", "Transform", "Undo", "Unknown", "Vec3", "VisualWords", "WebLookup",
    "datetime_from_timestamp", "is_timestamp", "iso_from_timestamp", "stored_type",
    "timestamp_from_datetime", "timestamp_from_iso",
]
