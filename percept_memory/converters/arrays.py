"""numpy arrays: dtype + shape + raw bytes, an exact round trip.

Exact means bit for bit: NaN payloads, -0.0, byte order (a big-endian array comes back
big-endian), 0-d and empty arrays, structured dtypes (point clouds) all survive.
"""

from __future__ import annotations

import numpy as np

from .blobs import ConversionError, DecodeContext, EncodeContext


def _as_tuples(descr):
    """BSON and JSON turn the tuples of a structured dtype description into lists; numpy wants
    each field as a tuple (name or (title, name), type, and a subarray's shape if any)."""
    if isinstance(descr, str):
        return descr
    if not isinstance(descr, list):  # numpy reads more (dicts, tuples), but not from us
        raise TypeError(f"a dtype is a string or a list of fields, not {type(descr).__name__}")
    if not all(isinstance(field, list | tuple) for field in descr):
        raise TypeError("each field of a structured dtype is a list: name, type (, shape)")
    fields = []
    for name, kind, *shape in descr:
        fields.append((tuple(name) if isinstance(name, list) else name, _as_tuples(kind),
                       *map(tuple, shape)))
    return fields


def dtype_of(descr) -> np.dtype:
    """The dtype a description (numpy's `dtype_to_descr`: "<f4", or a structured dtype's
    [name, type] pairs, as BSON and JSON keep them) stands for. Raises TypeError, ValueError."""
    try:
        return np.lib.format.descr_to_dtype(_as_tuples(descr))
    except SyntaxError:  # numpy parses "f4,i4"-like type strings as Python
        raise ValueError(f"{str(descr)[:40]!r} is not a dtype") from None


def encode_array_fields(array: np.ndarray, ctx: EncodeContext) -> dict:
    if array.dtype.hasobject:
        raise ConversionError("arrays of Python objects cannot be stored; use a numeric dtype")
    return {
        "dtype": np.lib.format.dtype_to_descr(array.dtype),
        "shape": list(array.shape),
        "data": ctx.binary(array.tobytes(order="C")),
    }


def decode_array_fields(doc: dict, ctx: DecodeContext) -> np.ndarray:
    try:
        dtype = dtype_of(doc["dtype"])
        flat = np.frombuffer(ctx.binary(doc["data"]), dtype=dtype)
        return flat.reshape(doc["shape"]).copy()  # a writable array the caller owns
    except (KeyError, TypeError, ValueError) as error:
        raise ConversionError(f"stored array is malformed: {error}") from error


class NDArrayCodec:
    """The foreign codec for `numpy.ndarray`."""

    name = "ndarray"

    def encode(self, array: np.ndarray, ctx: EncodeContext) -> dict:
        return {"_type": self.name, **encode_array_fields(array, ctx)}

    def decode(self, doc: dict, ctx: DecodeContext) -> np.ndarray:
        return decode_array_fields(doc, ctx)
