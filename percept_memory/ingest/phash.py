"""The 64-bit perceptual hash (pHash, thesis 5.4.5 [180]) of an image crop."""

from __future__ import annotations

import numpy as np

from percept_memory.memory.types.appearance import perceptual_hash


def crop_phash(bgr: np.ndarray) -> int:
    """The 64-bit pHash (imagehash's DCT hash) of a BGR (or grey) uint8 crop."""
    return int(perceptual_hash(bgr), 16)


def hamming(a: int, b: int) -> int:
    return (a ^ b).bit_count()
