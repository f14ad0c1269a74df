"""numpy arrays: dtype + shape + raw bytes, an exact round trip.

Exact means bit for bit: NaN payloads, -0.0, byte order (a big-endian array comes back
big-endian), 0-d and empty arrays, structured dtypes (point clouds) all survive.
"""

from __future__ import annotations

import numpy as np

from .blobs import ConversionError, DecodeContext, EncodeContext


def _as_tuples(descr):
    """BSON turns the tuples of a structured dtype description into lists; numpy wants tuples."""
    if isinstance(descr, list):
        return [tuple(_as_tuples(part) for part in field) for field in descr]
    return descr


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
        dtype = np.lib.format.descr_to_dtype(_as_tuples(doc["dtype"]))
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
