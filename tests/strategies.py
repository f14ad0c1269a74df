"""Hypothesis strategies for every registered type, derived from the type annotations.

Like the converter, this is written once: a new type gets random instances (respecting its
pydantic constraints) with no edit here, so the round-trip property covers it automatically.
"""

from __future__ import annotations

import types
import typing
from enum import Enum
from typing import Any

import numpy as np
from bson import ObjectId
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from pydantic import BaseModel, ValidationError
from pydantic.fields import FieldInfo

from percept_memory.converters import Unknown, registered_types
from percept_memory.memory.types import Image, PointCloud, Pose, SpatialVolume

# BSON strings are UTF-8: no lone surrogates.
TEXT = st.text(st.characters(exclude_categories=("Cs",)), max_size=12)
INT64 = st.integers(-(2**63), 2**63 - 1)

DTYPES = st.sampled_from(["<f4", ">f4", "<f8", ">f8", "<i4", ">i2", "|u1", "<u2", "|b1", "<c8"])
ARRAYS = DTYPES.flatmap(
    lambda dtype: hnp.arrays(np.dtype(dtype), hnp.array_shapes(min_dims=0, max_dims=3,
                                                                 min_side=0, max_side=5))
)
NAMED = {("u1", 1): "mono8", ("u1", 3): "rgb8", ("u1", 4): "bgra8", ("u2", 1): "mono16",
         ("u2", 3): "bgr16"}  # ROS' names of some of them, besides OpenCV's


def encoded_image(array: np.ndarray, fmt: str, named: bool) -> Image:
    """The pixels with an encoding that says what they are (ROS' name or OpenCV's)."""
    channels = array.shape[2] if array.ndim == 3 else 1
    kind = f"{array.dtype.kind}{array.dtype.itemsize}"
    cv = f"{array.dtype.itemsize * 8}{dict(u='U', i='S', f='F')[kind[0]]}C{channels}"
    encoding = NAMED.get((kind, channels), cv) if named else cv
    return Image(data=array, format=fmt, encoding=encoding)


IMAGES = st.builds(
    encoded_image,
    st.sampled_from([np.uint8, np.uint16, np.float32]).flatmap(
        lambda dtype: hnp.arrays(
            dtype,
            st.tuples(st.integers(1, 9), st.integers(1, 9))
            | st.tuples(st.integers(1, 9), st.integers(1, 9), st.sampled_from([1, 2, 3, 4])),
        )
    ),
    st.sampled_from(["png", "raw"]),
    st.booleans(),
)
POINT_CLOUDS = st.builds(
    PointCloud,
    points=hnp.arrays(np.float32, st.tuples(st.integers(0, 6), st.just(3)))
    | hnp.arrays(np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("rgb", "<u4")]),
                 st.integers(0, 6)),
    frame=TEXT,
)
UNIT_QUATERNIONS = st.tuples(*[st.floats(-1, 1)] * 4).filter(
    lambda q: sum(c * c for c in q) > 0.1
).map(lambda q: tuple(c / sum(x * x for x in q) ** 0.5 for c in q))
UNKNOWN = st.builds(
    lambda name, fields: Unknown(type_name=name, fields=fields),
    st.sampled_from(["rs.annotation.NotOurs", "future.Annotation", "x.y.Z"]),
    st.dictionaries(
        st.sampled_from(["a", "b", "confidence", "name"]),
        st.none() | st.booleans() | INT64 | TEXT | st.binary(max_size=8) | st.builds(ObjectId),
        max_size=4,
    ),
)

FINITE = st.floats(-1e3, 1e3)
CORNERS = st.tuples(*[st.tuples(FINITE, FINITE).map(sorted)] * 3).map(
    lambda axes: (tuple(lo for lo, _ in axes), tuple(hi for _, hi in axes)))
SPATIAL_VOLUMES = st.one_of(  # a box or a sphere, built so, not filtered from random draws
    st.builds(lambda frame, corners: SpatialVolume(frame=frame, box_min=corners[0],
                                                   box_max=corners[1]), TEXT, CORNERS),
    st.builds(SpatialVolume, frame=TEXT, center=st.tuples(FINITE, FINITE, FINITE),
              radius=st.floats(0, 1e3)),
)

SPECIAL: dict[Any, st.SearchStrategy] = {
    np.ndarray: ARRAYS,
    Image: IMAGES,
    PointCloud: POINT_CLOUDS,
    Unknown: UNKNOWN,
    SpatialVolume: SPATIAL_VOLUMES,
}


def _constraints(metadata: list) -> dict:
    found: dict = {}
    for item in metadata:
        if isinstance(item, FieldInfo):
            found.update(_constraints(item.metadata))
        for name in ("ge", "gt", "le", "lt", "pattern", "allow_inf_nan"):
            if getattr(item, name, None) is not None:
                found[name] = getattr(item, name)
    return found


def for_annotation(annotation: Any, metadata: list = ()) -> st.SearchStrategy:
    origin, args = typing.get_origin(annotation), typing.get_args(annotation)
    if origin is typing.Annotated:
        return for_annotation(args[0], [*metadata, *args[1:]])
    limits = _constraints(list(metadata))
    if annotation in SPECIAL:
        return SPECIAL[annotation]
    if origin is typing.Literal:
        return st.sampled_from(args)
    if origin in (typing.Union, types.UnionType):
        return st.one_of([for_annotation(arg, metadata) for arg in args])
    if origin is list:
        return st.lists(for_annotation(args[0]), max_size=3)
    if origin is dict:
        return st.dictionaries(TEXT, for_annotation(args[1]), max_size=3)
    if origin is tuple:
        if len(args) == 2 and args[1] is Ellipsis:
            return st.lists(for_annotation(args[0]), max_size=3).map(tuple)
        return st.tuples(*[for_annotation(arg) for arg in args])
    if annotation is type(None):
        return st.none()
    if annotation is bool:
        return st.booleans()
    if annotation is int:
        lo = limits.get("ge", limits["gt"] + 1 if "gt" in limits else -(2**63))
        hi = limits.get("le", limits["lt"] - 1 if "lt" in limits else 2**63 - 1)
        return st.integers(lo, hi)
    if annotation is float:
        bounded = any(k in limits for k in ("ge", "gt", "le", "lt"))
        return st.floats(
            min_value=limits.get("ge", limits.get("gt")),
            max_value=limits.get("le", limits.get("lt")),
            exclude_min="gt" in limits, exclude_max="lt" in limits,
            allow_nan=not bounded and limits.get("allow_inf_nan", True),
            allow_infinity=not bounded and limits.get("allow_inf_nan", True),
        )
    if annotation is str:
        return st.from_regex(limits["pattern"], fullmatch=True) if "pattern" in limits else TEXT
    if annotation is bytes:
        return st.binary(max_size=16)
    if annotation is ObjectId:
        return st.builds(ObjectId)
    if annotation is Any:
        return st.none() | INT64 | TEXT
    if isinstance(annotation, type) and issubclass(annotation, Enum):
        return st.sampled_from(list(annotation))
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return for_model(annotation)
    raise TypeError(f"no strategy for {annotation!r}")


def _concrete(cls: type) -> list[type]:
    return [t for t in registered_types().values() if issubclass(t, cls)]


def _build(cls: type, values: dict) -> Any:
    try:
        return cls(**values)
    except ValidationError:
        return None  # values that break a model-level rule (e.g. box or sphere): drawn again


def for_model(cls: type) -> st.SearchStrategy:
    """Valid instances of `cls`, or of its registered subclasses when `cls` is a base."""
    if cls in SPECIAL:
        return SPECIAL[cls]
    if cls not in registered_types().values():
        return st.one_of([st.deferred(lambda t=t: for_model(t)) for t in _concrete(cls)])
    required, optional = {}, {}
    for name, info in cls.model_fields.items():
        strategy = for_annotation(info.annotation, info.metadata)
        if issubclass(cls, Pose) and name == "rotation":
            strategy = UNIT_QUATERNIONS
        (required if info.is_required() else optional)[name] = strategy
    return (
        st.fixed_dictionaries(required, optional=optional)
        .map(lambda values: _build(cls, values))
        .filter(lambda obj: obj is not None)
    )
