"""The 64-bit perceptual hash (pHash, thesis 5.4.5 [180]) of an image crop."""

from __future__ import annotations

import imagehash
import numpy as np
from PIL import Image as PILImage


def crop_phash(bgr: np.ndarray) -> int:
    """The 64-bit pHash (imagehash's DCT hash) of a BGR (or grey) uint8 crop."""
    rgb = np.ascontiguousarray(bgr[..., ::-1]) if bgr.ndim == 3 else bgr
    return int(str(imagehash.phash(PILImage.fromarray(rgb))), 16)


def hamming(a: int, b: int) -> int:
    return (a ^ b).bit_count()
