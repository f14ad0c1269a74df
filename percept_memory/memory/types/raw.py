"""Raw data types (thesis 3.2.1): arrays, images, point clouds, poses, camera intrinsics."""

from __future__ import annotations

import math
import re
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import (
    Field,
    PlainSerializer,
    PlainValidator,
    PrivateAttr,
    ValidationInfo,
    WithJsonSchema,
    field_validator,
    model_validator,
)

from percept_memory.converters import ImageCodec, register_codec
from percept_memory.converters.images import PNG_SIGNATURE

from .base import Model, Timestamp, stored_type
from .json_forms import (
    array_from_json,
    array_to_json,
    image_from_json,
    image_limit,
    image_to_json,
)

NDArray = Annotated[
    np.ndarray,
    PlainValidator(array_from_json),
    PlainSerializer(array_to_json, when_used="json"),
    WithJsonSchema({
        "description": "numbers: nested lists, {dtype, shape, base64} (exact), or {path} of a "
                       ".npy file in the scene-log folder",
        "anyOf": [
            {"type": "array"},
            {"type": "object", "required": ["dtype", "shape", "base64"], "properties": {
                "dtype": {"description": "numpy's description of the dtype: a string, or a "
                                         "structured dtype's [name, type] pairs",
                          "anyOf": [{"type": "string"}, {"type": "array"}],
                          "examples": ["<f4", "|u1", [["x", "<f4"], ["y", "<f4"]]]},
                "shape": {"type": "array", "items": {"type": "integer", "minimum": 0}},
                "base64": {"type": "string", "contentEncoding": "base64"}},
             "additionalProperties": False},
            {"type": "object", "required": ["path"], "properties": {"path": {"type": "string"}},
             "additionalProperties": False},
        ],
    }),
]
"""A numpy array of numbers, stored exactly (dtype, shape, bytes)."""

UNIT = 1e-12  # a quaternion this close to length 1 is a unit quaternion
Finite = Annotated[float, Field(allow_inf_nan=False)]
Vec3 = tuple[Finite, Finite, Finite]
"""x, y, z in metres."""
Quaternion = tuple[Finite, Finite, Finite, Finite]
"""x, y, z, w."""
NonNegative = Annotated[int, Field(ge=0)]
Box = tuple[NonNegative, NonNegative, NonNegative, NonNegative]
"""An image rectangle: x, y, width, height in pixels."""


@stored_type("pm.raw.Pose", aliases=("rs.tf.StampedPose",))
class Pose(Model):
    """A position and orientation in a named frame (tf-style, quaternion x, y, z, w)."""

    translation: Vec3 = (0.0, 0.0, 0.0)
    rotation: Quaternion = (0.0, 0.0, 0.0, 1.0)
    frame: str = "map"
    stamp: Timestamp | None = None

    @field_validator("rotation")
    @classmethod
    def _unit_quaternion(cls, rotation: Quaternion) -> Quaternion:
        norm = math.sqrt(sum(c * c for c in rotation))
        if not 0.5 < norm < 1.5:
            raise ValueError(f"rotation quaternion must have length 1, has {norm:.3g}")
        if abs(norm - 1) <= UNIT:  # unit already: dividing again moves its last digits, and a
            return rotation  # scene written out and read back would not be the same scene
        return tuple(c / norm for c in rotation)  # type: ignore[return-value]

    def matrix(self) -> np.ndarray:
        """The 4x4 homogeneous transform of this pose."""
        x, y, z, w = self.rotation
        rotation = np.array([
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ])
        result = np.eye(4)
        result[:3, :3] = rotation
        result[:3, 3] = self.translation
        return result


@stored_type("pm.raw.Transform", aliases=("rs.tf.StampedTransform",))
class Transform(Pose):
    """The pose of `child_frame` in `frame`, e.g. the camera in the map."""

    child_frame: str


@stored_type("pm.raw.CameraInfo")
class CameraInfo(Model):
    """Pinhole intrinsics, as in ROS sensor_msgs/CameraInfo."""

    width: Annotated[int, Field(gt=0)]
    height: Annotated[int, Field(gt=0)]
    k: tuple[Finite, Finite, Finite, Finite, Finite, Finite, Finite, Finite, Finite]
    d: list[Finite] = []
    distortion_model: str = "plumb_bob"
    frame: str = ""

    @property
    def focal(self) -> tuple[float, float]:
        return self.k[0], self.k[4]

    @property
    def principal_point(self) -> tuple[float, float]:
        return self.k[2], self.k[5]

    def back_project(self, u: np.ndarray, v: np.ndarray, z: np.ndarray) -> np.ndarray:
        """The (N, 3) points in the camera frame seen at pixels (u, v) at depths z (metres):
        how a depth image becomes a cloud."""
        (fx, fy), (cx, cy) = self.focal, self.principal_point
        return np.stack([(u - cx) * z / fx, (v - cy) * z / fy, z], axis=-1)


@stored_type("pm.raw.Image")
class Image(Model):
    """An image array with its ROS-style encoding; stored as lossless PNG unless asked.

    In JSON the pixels come as `png` or `jpeg` (base64), as a `path` to an image file in the
    scene-log folder, or as `data` (an array); e.g. {"png": "iVBORw0...", "encoding": "bgr8"}.
    """

    data: NDArray
    encoding: str = "bgr8"
    format: Literal["png", "jpeg", "raw"] = "png"
    _given_file: tuple[np.ndarray, str, bytes] | None = PrivateAttr(default=None)

    @model_validator(mode="wrap")
    @classmethod
    def _decode_files(cls, data: Any, handler, info: ValidationInfo) -> Image:
        fields, file = image_from_json(data, info)
        image = handler(fields)
        if file is not None and image.data is fields["data"]:
            image.data.flags.writeable = False  # the pixels stay what the file holds
            image._given_file = (image.data, image.encoding, file)
        return image

    @property
    def file(self) -> bytes | None:
        """The PNG or JPEG file (as `format` says) the pixels were read from, when they still
        are its pixels and it is no larger than they are: the store keeps it as it is instead
        of encoding the pixels again (decoding it gives them back exactly)."""
        if self._given_file is None:
            return None
        data, encoding, file = self._given_file
        kind = "png" if file.startswith(PNG_SIGNATURE) else "jpeg"
        if (self.data is data and self.encoding == encoding and self.format == kind
                and len(file) <= data.nbytes):
            return file
        return None

    def _json_fields(self, fields: dict) -> dict:
        return image_to_json(fields, self.data)

    @classmethod
    def __get_pydantic_json_schema__(cls, core_schema, handler) -> dict:
        """The forms JSON brings the pixels in, exactly one of them (the model's own field,
        `data`, is one)."""
        schema = super().__get_pydantic_json_schema__(core_schema, handler)
        target = handler.resolve_ref_schema(schema)
        base64 = {"type": "string", "contentEncoding": "base64"}
        target["properties"] |= {
            "png": {**base64, "description": "a PNG file, base64"},
            "jpeg": {**base64, "description": "a JPEG file, base64"},
            "path": {"type": "string", "description": "a PNG or JPEG file in the scene-log "
                                                      "folder, relative to it"}}
        target.pop("required", None)
        target["oneOf"] = [{"required": [form]} for form in ("data", "png", "jpeg", "path")]
        return schema

    @field_validator("data")
    @classmethod
    def _image_shaped(cls, data: np.ndarray, info: ValidationInfo) -> np.ndarray:
        if data.ndim not in (2, 3):
            raise ValueError(
                f"an image is 2-D or 3-D (height, width[, channels]), got {data.ndim}-D"
            )
        if data.size == 0:
            raise ValueError(f"an image has pixels; this one is {data.shape}")
        check_pixels(data, image_limit(info))
        return data

    @model_validator(mode="after")
    def _pixels_as_encoded(self) -> Image:
        if problem := encoding_problem(self.encoding, self.data):
            raise ValueError(problem)
        return self

    @property
    def height(self) -> int:
        return self.data.shape[0]

    @property
    def width(self) -> int:
        return self.data.shape[1]


register_codec(Image, ImageCodec(Image, "pm.raw.Image"))


# ROS' image encodings (sensor_msgs/image_encodings.h): the pixels' channels and their type
NAMED_ENCODINGS = {
    **{f"{name}{bits}": (channels, f"u{bits // 8}") for bits in (8, 16)
       for name, channels in (("mono", 1), ("bgr", 3), ("rgb", 3), ("bgra", 4), ("rgba", 4))},
    **{f"bayer_{order}{bits}": (1, f"u{bits // 8}") for bits in (8, 16)
       for order in ("rggb", "bggr", "gbrg", "grbg")},
    "yuv422": (2, "u1"),
}
CV_ENCODING = re.compile(r"(8|16|32|64)([USF])C([1-4])")  # 16UC1, 32FC1: OpenCV's names
CV_KINDS = {"U": "u", "S": "i", "F": "f"}


def encoding_problem(encoding: str, data: np.ndarray) -> str | None:
    """Why the pixels are not what the encoding says (channels, type), or None. An encoding
    stored against its pixels misleads every reader (a mono8 of three channels)."""
    if (cv := CV_ENCODING.fullmatch(encoding)) is not None:
        channels, kind = int(cv[3]), f"{CV_KINDS[cv[2]]}{int(cv[1]) // 8}"
    elif encoding in NAMED_ENCODINGS:
        channels, kind = NAMED_ENCODINGS[encoding]
    else:
        return (f"encoding {encoding!r} is not an image encoding: one of ROS' (mono8, mono16, "
                "bgr8, rgb8, bgra8, rgba8, bgr16, ..., bayer_rggb8, yuv422) or OpenCV's "
                "(8UC3, 16UC1, 32FC1, ...)")
    has = data.shape[2] if data.ndim == 3 else 1
    if (has, f"{data.dtype.kind}{data.dtype.itemsize}") != (channels, kind):
        return (f"encoding {encoding!r} is {channels} channel(s) of {np.dtype(kind)}, but the "
                f"pixels are {has} channel(s) of {data.dtype}")
    return None


def check_pixels(data: np.ndarray, limit: int) -> None:
    """Refuse an image of more than `limit` pixels (each view of it would cost its size)."""
    height, width = data.shape[:2]
    if height * width > limit:
        raise ValueError(f"the image is {width} x {height} pixels, over the limit of {limit}")


@stored_type("pm.raw.PointCloud")
class PointCloud(Model):
    """Points in a frame: an (N, 3) float array or a structured array with fields x, y, z
    (plus rgb, normals, ... as the sensor gives them)."""

    points: NDArray
    frame: str = ""

    @field_validator("points")
    @classmethod
    def _has_xyz(cls, points: np.ndarray) -> np.ndarray:
        names = points.dtype.names
        if names is not None:
            if not {"x", "y", "z"} <= set(names):
                raise ValueError(f"structured points need fields x, y, z; got {names}")
        elif points.ndim != 2 or points.shape[1] != 3:
            raise ValueError(
                f"points must be (N, 3) or structured with x, y, z; got {points.shape}"
            )
        return points

    def xyz(self) -> np.ndarray:
        """The coordinates as an (N, 3) float array."""
        if self.points.dtype.names is None:
            return np.asarray(self.points, dtype=float)
        return np.stack([self.points[c].astype(float) for c in "xyz"], axis=-1)

    def bgr(self) -> np.ndarray | None:
        """The (N, 3) uint8 colours of PCL's packed `rgb`/`rgba` field (blue, green, red, as
        OpenCV orders them), or None when the points have no colour."""
        name = next((n for n in ("rgb", "rgba") if n in (self.points.dtype.names or ())), None)
        if name is None:
            return None
        packed = np.ascontiguousarray(self.points[name]).view(np.uint32)
        return np.stack([packed & 255, (packed >> 8) & 255, (packed >> 16) & 255],
                        axis=1).astype(np.uint8)
