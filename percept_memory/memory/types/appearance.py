"""Descriptors as vectors: what similarity search indexes (memory/similarity.py).

A type declares its descriptors in its own class (`descriptors()`, name -> vector), each a unit
vector whose inner product with another of the same name is how alike the two look, in the
same sense as the type's `similarities` (compare.py): a histogram's square roots (Bhattacharyya
overlap), a feature vector's direction (cosine). This module holds the ones computed from
pixels, with OpenCV: so an uploaded image is described exactly as a stored crop is.
"""

from __future__ import annotations

import cv2
import imagehash
import numpy as np
from PIL import Image as PILImage

SIDE = 32  # crops are compared at this size: what they show, not how many pixels they have
HUE_BINS, SATURATION_BINS = 12, 4
CELLS, ORIENTATIONS = 4, 9  # gradients: 4 x 4 cells of 8 x 8 pixels, 9 orientations each


def unit(vector: np.ndarray) -> np.ndarray | None:
    """The vector scaled to length 1 (None for a zero vector: nothing to say)."""
    vector = np.asarray(vector, dtype=np.float64).ravel()
    norm = np.linalg.norm(vector)
    return vector / norm if norm > 0 else None


def sqrt_distribution(histogram: np.ndarray) -> np.ndarray | None:
    """The square roots of a histogram normalised to sum 1: their inner product is the
    Bhattacharyya overlap (as ColorHistogram.similarities computes it)."""
    p = np.clip(np.asarray(histogram, dtype=np.float64).ravel(), 0, None)
    total = p.sum()
    return np.sqrt(p / total) if total > 0 else None


def hash_bits(phash: str) -> np.ndarray:
    """A 64-bit hash in hex as +-1/8 per bit: the inner product of two is 1 - 2 h / 64 for
    Hamming distance h (1 the same hash, 0 unrelated, -1 every bit differs)."""
    bits = np.unpackbits(np.frombuffer(int(phash, 16).to_bytes(8, "big"), np.uint8))
    return (bits * 2.0 - 1) / 8


def perceptual_hash(bgr: np.ndarray) -> str:
    """The 64-bit pHash (imagehash's DCT hash) of a crop (BGR, grey or BGRA), in hex."""
    return str(imagehash.phash(PILImage.fromarray(np.ascontiguousarray(_bgr(bgr)[..., ::-1]))))


def _bgr(pixels: np.ndarray) -> np.ndarray:
    """A crop as 8-bit BGR (grey and BGRA crops too)."""
    if pixels.dtype != np.uint8:
        pixels = cv2.normalize(pixels, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    if pixels.ndim == 2 or pixels.shape[2] == 1:
        return cv2.cvtColor(pixels, cv2.COLOR_GRAY2BGR)
    return np.ascontiguousarray(pixels[..., :3])


def gradient_histograms(grey: np.ndarray) -> np.ndarray:
    """A histogram of oriented gradients (Dalal and Triggs' HOG without block normalisation):
    per cell, the gradient magnitude summed per unsigned orientation. OpenCV 5 dropped its
    HOGDescriptor from the main package, and this much is not worth scikit-image's four
    dependencies."""
    gx = cv2.Sobel(grey, cv2.CV_32F, 1, 0, ksize=1)
    gy = cv2.Sobel(grey, cv2.CV_32F, 0, 1, ksize=1)
    magnitude, angle = cv2.cartToPolar(gx, gy, angleInDegrees=True)
    orientation = (angle % 180 * ORIENTATIONS / 180).astype(int) % ORIENTATIONS
    side = grey.shape[0] // CELLS
    cell = (np.arange(grey.shape[0]) // side)[:, None] * CELLS + np.arange(grey.shape[1]) // side
    return np.bincount((cell * ORIENTATIONS + orientation).ravel(), magnitude.ravel(),
                       CELLS * CELLS * ORIENTATIONS)


def crop_descriptors(pixels: np.ndarray, mask: np.ndarray | None = None
                     ) -> dict[str, np.ndarray]:
    """What a crop looks like: `crop-colour`, a hue-saturation histogram of its (masked)
    pixels, and `crop-hog`, the histogram of oriented gradients of its outline and print."""
    bgr = cv2.resize(_bgr(pixels), (SIDE, SIDE), interpolation=cv2.INTER_AREA)
    inside = None
    if mask is not None and mask.shape[:2] == pixels.shape[:2]:
        inside = cv2.resize((mask.reshape(mask.shape[:2]) > 0).astype(np.uint8), (SIDE, SIDE),
                            interpolation=cv2.INTER_NEAREST)
        inside = inside if inside.any() else None
    hsv = cv2.cvtColor(bgr, cv2.COLOR_BGR2HSV)
    colour = cv2.calcHist([hsv], [0, 1], inside, [HUE_BINS, SATURATION_BINS], [0, 180, 0, 256])
    gradients = gradient_histograms(cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY))
    found = {"crop-colour": sqrt_distribution(colour), "crop-hog": unit(gradients)}
    return {name: vector for name, vector in found.items() if vector is not None}
