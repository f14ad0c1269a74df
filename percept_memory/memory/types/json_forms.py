"""How arrays and images travel in JSON (scene interchange format v1).

An array is given as nested lists of numbers, as `{"dtype": "<f4", "shape": [308],
"base64": "..."}` (exact: any dtype, NaN, byte order; a structured dtype, such as a point
cloud's x, y, z, rgb, as numpy describes it: [["x", "<f4"], ...]), or as
`{"path": "arrays/vfh.npy"}`.
An image is given as `{"png": "<base64>"}`, `{"jpeg": "<base64>"}`, `{"path": "rgb.png"}`,
or as `{"data": <array>}`, each with its `encoding`. Paths are relative to the scene-log folder
the scene was read from (passed to validation as context `{"folder": Path}`) and may not leave
it. Written out, arrays take the base64 form and images the PNG form where PNG holds them.
"""

from __future__ import annotations

import base64
import binascii
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import ValidationInfo

from percept_memory.converters import ConversionError
from percept_memory.converters.arrays import dtype_of
from percept_memory.converters.images import compress, decode_file, png_compatible

MAX_ARRAY_BYTES = 512 * 2**20  # one value; a whole HTTP request is limited separately
IMAGE_FORMATS = ("png", "jpeg")
IMAGE_LIMITS = {"max_image_pixels": 40_000_000, "max_crop_pixels": 4_000_000}  # defaults


def resolve_path(relative: Any, info: ValidationInfo) -> Path:
    """The file a relative path names inside the scene-log folder being read."""
    folder = (info.context or {}).get("folder")
    if folder is None:
        raise ValueError("a path needs a scene-log folder to be relative to; send base64 instead")
    if not isinstance(relative, str) or not relative or Path(relative).is_absolute():
        raise ValueError(f"path must be a relative file path, got {relative!r}")
    root = Path(folder).resolve()
    target = (root / relative).resolve()
    if not target.is_relative_to(root):
        raise ValueError(f"path {relative!r} leaves the scene-log folder")
    if not target.is_file():
        raise ValueError(f"no file {relative!r} in the scene-log folder")
    if target.stat().st_size > MAX_ARRAY_BYTES:
        raise ValueError(f"file {relative!r} is larger than {MAX_ARRAY_BYTES} bytes")
    return target


def decode_base64(text: Any, what: str) -> bytes:
    if not isinstance(text, str):
        raise ValueError(f"{what} must be a base64 string")
    if len(text) * 3 // 4 > MAX_ARRAY_BYTES:
        raise ValueError(f"{what} is larger than {MAX_ARRAY_BYTES} bytes")
    try:
        return base64.b64decode(text, validate=True)
    except (binascii.Error, ValueError):
        raise ValueError(f"{what} is not valid base64") from None


def array_from_json(value: Any, info: ValidationInfo) -> np.ndarray:
    """An array from any of its JSON forms (or an ndarray given directly)."""
    if isinstance(value, np.ndarray):
        array = value
    elif isinstance(value, dict) and set(value) == {"path"}:
        try:
            array = np.load(resolve_path(value["path"], info), allow_pickle=False)
        except (OSError, ValueError) as error:
            raise ValueError(f"{value['path']!r} is not a readable .npy file: {error}") from None
    elif isinstance(value, dict):
        array = _array_from_base64(value)
    else:
        array = np.asarray(value)
        if array.dtype.kind not in "biufc":
            raise ValueError("an array holds numbers only (nested lists of equal length)")
    if array.dtype.hasobject:
        raise ValueError("arrays must hold numbers, not Python objects")
    if array.nbytes > MAX_ARRAY_BYTES:
        raise ValueError(f"array of {array.nbytes} bytes is larger than {MAX_ARRAY_BYTES}")
    return array


def _array_from_base64(value: dict) -> np.ndarray:
    if set(value) != {"dtype", "shape", "base64"}:
        raise ValueError("an array object has exactly the keys dtype, shape and base64 (or path)")
    try:
        dtype = dtype_of(value["dtype"])
    except (TypeError, ValueError, KeyError, IndexError):
        raise ValueError(f"unknown dtype {str(value['dtype'])[:80]}") from None
    shape = value["shape"]
    if not isinstance(shape, list) or not all(isinstance(n, int) and n >= 0 for n in shape):
        raise ValueError("shape must be a list of non-negative integers")
    if dtype.hasobject or dtype.itemsize == 0:
        raise ValueError(f"dtype {value['dtype']!r} cannot be stored")
    expected = int(np.prod(shape, dtype=object)) * dtype.itemsize
    if expected > MAX_ARRAY_BYTES:
        raise ValueError(f"shape {shape} of {dtype} is larger than {MAX_ARRAY_BYTES} bytes")
    data = decode_base64(value["base64"], "base64")
    if len(data) != expected:
        raise ValueError(f"shape {shape} of {dtype} needs {expected} bytes, base64 has {len(data)}")
    return np.frombuffer(data, dtype=dtype).reshape(shape).copy()


def array_to_json(array: np.ndarray) -> dict:
    return {
        "dtype": np.lib.format.dtype_to_descr(array.dtype),
        "shape": list(array.shape),
        "base64": base64.b64encode(np.ascontiguousarray(array).tobytes()).decode(),
    }


def image_from_json(data: Any, info: ValidationInfo) -> tuple[Any, bytes | None]:
    """Image fields with the pixels decoded from PNG/JPEG (base64 or a file), and the PNG or
    JPEG bytes they were decoded from (None when the pixels came as an array)."""
    if not isinstance(data, dict):
        return data, None
    given = [key for key in (*IMAGE_FORMATS, "path") if key in data]
    if not given:
        return data, None
    if len(given) > 1 or "data" in data:
        raise ValueError("give an image's pixels once: data, png, jpeg or path")
    key = given[0]
    fields = {k: v for k, v in data.items() if k != key}
    if key == "path":
        encoded = resolve_path(data["path"], info).read_bytes()
        fields.setdefault("format", "jpeg" if data["path"].lower().endswith((".jpg", ".jpeg"))
                          else "png")
    else:
        encoded = decode_base64(data[key], key)
        fields.setdefault("format", key)
    try:
        pixels = decode_file(encoded, fields.get("encoding", "bgr8"), image_limit(info))
    except ConversionError as error:
        what = f"image file {data['path']!r}" if key == "path" else f"{key} image"
        raise ValueError(f"the {what} {error}") from None
    return {**fields, "data": pixels}, encoded


def image_limit(info: ValidationInfo, kind: str = "max_image_pixels") -> int:
    """The most pixels an image (or, kind max_crop_pixels, a crop) may have: the validation
    context's (from the settings, PMEM_MAX_IMAGE_PIXELS and PMEM_MAX_CROP_PIXELS), else the
    default."""
    return (info.context or {}).get(kind, IMAGE_LIMITS[kind])


def image_to_json(fields: dict, pixels: np.ndarray) -> dict:
    """The JSON form of an image: PNG where PNG holds it exactly, else the array form."""
    if png_compatible(pixels):
        png = compress(pixels, fields.get("encoding", "bgr8"), "png")
        return {**{k: v for k, v in fields.items() if k != "data"},
                "png": base64.b64encode(png).decode()}
    return {**fields, "data": array_to_json(pixels)}
