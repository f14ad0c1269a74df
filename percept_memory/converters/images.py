"""Images: lossless PNG by default, JPEG on request, raw bytes when PNG cannot hold them.

The codec works for any image model with the fields `data` (numpy array), `encoding`
(ROS-style: rgb8, bgr8, mono8, mono16, 32FC1, ...) and `format` ("png", "jpeg", "raw").
PNG files are written with the right colour order, so a stored PNG opens correctly anywhere.
An image model may also have `file`: PNG or JPEG bytes of its `format` that decode to exactly
its `data` (the file it was read from), stored as they are instead of encoding `data` again.
"""

from __future__ import annotations

import struct
from functools import cache
from typing import Any

import numpy as np

from .arrays import decode_array_fields, encode_array_fields
from .blobs import ConversionError, DecodeContext, EncodeContext

JPEG_QUALITY = 95


@cache
def _opencv():
    """OpenCV, loaded by the first image coded (commands that code none, such as `pmem query`,
    start without it)."""
    import cv2

    return cv2


@cache
def _png_params() -> list[int]:
    """Chosen by measurement on 64 px crops of the real kitchen frame: Huffman coding after
    the SUB filter takes 141 us and 7.3 kB per crop; the default adaptive filter 269 us and
    6.9 kB. PNG is lossless whatever the settings."""
    cv2 = _opencv()
    return [cv2.IMWRITE_PNG_COMPRESSION, 1,
            cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_HUFFMAN_ONLY,
            cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_SUB]


def png_compatible(array: np.ndarray) -> bool:
    """Can PNG hold this array bit-exactly? (8/16-bit native unsigned, 1, 3 or 4 channels.)"""
    channels_ok = array.ndim == 2 or (array.ndim == 3 and array.shape[2] in (1, 3, 4))
    return (
        channels_ok
        and array.dtype in (np.dtype(np.uint8), np.dtype(np.uint16))
        and array.size > 0
    )


def _swaps_channels(encoding: str, array: np.ndarray) -> bool:
    return encoding.startswith("rgb") and array.ndim == 3 and array.shape[2] in (3, 4)


def compress(array: np.ndarray, encoding: str, fmt: str) -> bytes:
    """PNG or JPEG bytes of an image array."""
    if _swaps_channels(encoding, array):
        array = array[..., [2, 1, 0, 3][: array.shape[2]]]
    if fmt == "png":
        ok, buffer = _opencv().imencode(".png", array, _png_params())
    elif fmt == "jpeg":
        if array.dtype != np.uint8 or array.ndim == 3 and array.shape[2] == 4:
            raise ConversionError("JPEG holds 8-bit grey or colour images only; use png")
        cv2 = _opencv()
        ok, buffer = cv2.imencode(".jpg", array, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
    else:
        raise ConversionError(f"unknown image format {fmt!r}")
    if not ok:
        raise ConversionError(f"OpenCV could not encode the image as {fmt}")
    return buffer.tobytes()


def image_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) of PNG or JPEG bytes read from the header (PNG's IHDR chunk, JPEG's
    start-of-frame segment) without decoding a pixel; None for anything else."""
    if data.startswith(PNG_SIGNATURE) and data[12:16] == b"IHDR" and len(data) >= 24:
        return struct.unpack(">II", data[16:24])
    if not data.startswith(b"\xff\xd8"):
        return None
    at = 2
    while at + 9 <= len(data) and data[at] == 0xFF:
        marker, length = data[at + 1], struct.unpack(">H", data[at + 2:at + 4])[0]
        if marker in JPEG_FRAME_MARKERS:
            height, width = struct.unpack(">HH", data[at + 5:at + 9])
            return width, height
        at += 2 + length
    return None


PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
JPEG_FRAME_MARKERS = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE,
                      0xCF}  # SOF0-15 but DHT, JPG and DAC


def decode_file(data: bytes, encoding: str, max_pixels: int | None = None) -> np.ndarray:
    """The pixels of PNG or JPEG bytes, in the channel order `encoding` names (files hold BGR).
    With `max_pixels`, the size in the header is checked first: decoding a small file can
    take gigabytes."""
    if not data:
        raise ConversionError("is empty (0 bytes)")
    if max_pixels is not None:
        size = image_size(data)
        if size is None:
            raise ConversionError("does not decode (not a PNG or JPEG image)")
        if size[0] * size[1] > max_pixels:
            raise ConversionError(f"is {size[0]} x {size[1]} pixels, over the limit of "
                                  f"{max_pixels}")
    cv2 = _opencv()
    array = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if array is None:
        raise ConversionError("does not decode")
    if _swaps_channels(encoding, array):
        array = array[..., [2, 1, 0, 3][: array.shape[2]]].copy()
    return array


def decompress(data: bytes, encoding: str, shape: list[int], dtype: str) -> np.ndarray:
    """The image array back from PNG or JPEG bytes, in the shape and dtype it was stored with."""
    return decode_file(data, encoding).reshape(shape).astype(np.dtype(dtype), copy=False)


class ImageCodec:
    """Foreign codec for an image model class (see module docstring)."""

    def __init__(self, cls: type, name: str):
        self.cls = cls
        self.name = name

    def encode(self, image: Any, ctx: EncodeContext) -> dict:
        array, fmt = image.data, image.format
        lossless_raw = fmt == "raw" or (fmt == "png" and not png_compatible(array))
        stored_as = "raw" if lossless_raw else fmt
        doc = {
            "_type": self.name, "encoding": image.encoding, "format": fmt, "stored_as": stored_as
        }
        if stored_as == "raw":
            doc.update(encode_array_fields(array, ctx))
        else:
            doc["dtype"] = array.dtype.str
            doc["shape"] = list(array.shape)
            file = getattr(image, "file", None) or compress(array, image.encoding, fmt)
            doc["data"] = ctx.binary(file)
        return doc

    def decode(self, doc: dict, ctx: DecodeContext) -> Any:
        try:
            if doc["stored_as"] == "raw":
                array = decode_array_fields(doc, ctx)
            else:
                data = ctx.binary(doc["data"])
                array = decompress(data, doc["encoding"], doc["shape"], doc["dtype"])
            return self.cls.model_construct(
                data=array, encoding=doc["encoding"], format=doc["format"]
            )
        except KeyError as error:
            raise ConversionError(f"stored image lacks {error}") from error
