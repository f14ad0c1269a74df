"""Stored images as PNG files a browser can show: any encoding and depth, optionally shrunk."""

from __future__ import annotations

import cv2
import numpy as np

from percept_memory.converters.images import compress
from percept_memory.memory.types import Image


def display_png(image: Image, max_side: int | None = None) -> bytes:
    """The image as 8-bit PNG. Depth and float images are stretched over their finite range
    (a browser shows 16-bit PNGs, but a depth map in millimetres looks black)."""
    array = image.data
    if array.dtype != np.uint8:
        array = _stretched(array)
    if max_side and max(array.shape[:2]) > max_side:
        scale = max_side / max(array.shape[:2])
        size = (max(1, round(array.shape[1] * scale)), max(1, round(array.shape[0] * scale)))
        array = cv2.resize(array, size, interpolation=cv2.INTER_AREA)
    return compress(array, image.encoding, "png")


def _stretched(array: np.ndarray) -> np.ndarray:
    values = array.astype(float)
    finite = np.isfinite(values)
    if not finite.any():
        return np.zeros(array.shape, np.uint8)
    low, high = values[finite].min(), values[finite].max()
    scaled = (values - low) / (high - low) * 255 if high > low else np.zeros_like(values)
    return np.where(finite, scaled, 0).astype(np.uint8)
