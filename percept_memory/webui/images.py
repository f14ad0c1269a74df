"""Stored images as PNG files a browser can show: any encoding and depth, optionally shrunk."""

from __future__ import annotations

import cv2
import numpy as np

from percept_memory.converters.images import compress
from percept_memory.memory.types import Image


def display_png(image: Image, max_side: int | None = None) -> bytes:
    """The image as 8-bit PNG. A single-channel image of more than 8 bits (a depth map) is
    shown in false colour (depth_range), other deep images are stretched over their finite
    range: a browser shows 16-bit PNGs, but a depth map in millimetres looks black."""
    array, encoding = image.data, image.encoding
    if array.dtype != np.uint8 and array.ndim == 2:
        array, encoding = false_colour(array), "bgr8"
    elif array.dtype != np.uint8:
        array = _stretched(array)
    if max_side and max(array.shape[:2]) > max_side:
        scale = max_side / max(array.shape[:2])
        size = (max(1, round(array.shape[1] * scale)), max(1, round(array.shape[0] * scale)))
        array = cv2.resize(array, size, interpolation=cv2.INTER_AREA)
    return compress(array, encoding, "png")


def is_depth(image: Image) -> bool:
    """Shown in false colour: one channel of more than 8 bits (millimetres, metres, ...)."""
    return image.data.ndim == 2 and image.data.dtype != np.uint8


def depth_range(array: np.ndarray) -> tuple[float, float] | None:
    """The nearest and farthest reading; 0 and non-finite values are no reading. None when
    the image has no reading at all."""
    valid = array[np.isfinite(array) & (array != 0)]
    return (float(valid.min()), float(valid.max())) if valid.size else None


def false_colour(array: np.ndarray) -> np.ndarray:
    """Turbo colours from near (blue) to far (red) over the readings' range, no reading
    black: shape and distance at a glance, where grey levels hide both."""
    span = depth_range(array)
    if span is None:
        return np.zeros((*array.shape, 3), np.uint8)
    low, high = span
    values = np.nan_to_num(array.astype(np.float32), nan=0.0, posinf=0.0, neginf=0.0)
    scaled = (values - low) / ((high - low) or 1.0) * 255
    coloured = cv2.applyColorMap(np.clip(scaled, 0, 255).astype(np.uint8), cv2.COLORMAP_TURBO)
    coloured[values == 0] = 0
    return coloured


def _stretched(array: np.ndarray) -> np.ndarray:
    values = array.astype(float)
    finite = np.isfinite(values)
    if not finite.any():
        return np.zeros(array.shape, np.uint8)
    low, high = values[finite].min(), values[finite].max()
    scaled = (values - low) / (high - low) * 255 if high > low else np.zeros_like(values)
    return np.where(finite, scaled, 0).astype(np.uint8)
