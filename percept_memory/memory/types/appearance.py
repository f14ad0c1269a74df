"""Descriptors as vectors: what similarity search indexes (memory/similarity.py).

A type declares its descriptors in its own class (`descriptors()`, name -> vector), each a unit
vector whose inner product with another of the same name is how alike the two look, in the
same sense as the type's `similarities` (compare.py): a histogram's square roots (Bhattacharyya
overlap), a feature vector's direction (cosine). This module holds the ones computed from
pixels, with OpenCV: so an uploaded image is described exactly as a stored crop is.
"""

from __future__ import annotations

import functools
from pathlib import Path

import cv2
import imagehash
import numpy as np
from PIL import Image as PILImage

SIDE = 32  # crops are compared at this size: what they show, not how many pixels they have
HUE_BINS, SATURATION_BINS = 12, 4
CELLS, ORIENTATIONS = 4, 9  # gradients: 4 x 4 cells of 8 x 8 pixels, 9 orientations each
# ORB keypoints are found on crops scaled to this side: a 64 px crop has room for 15 px patches
# over three pyramid levels (ORB's default 31 px patches leave a 64 px crop 2 px to look in).
ORB_SIDE = 96
ORB_PARAMETERS = {"nfeatures": 100, "edgeThreshold": 15, "patchSize": 15, "nlevels": 3,
                  "fastThreshold": 10}
VOCABULARY = Path(__file__).with_name("orb_vocabulary.npz")  # orb_vocabulary.py makes it
ORB_DESCRIPTOR = "crop-orb"
# OpenCV splits even a 96 px image's work across its thread pool: no less CPU (~0.35 ms a
# textured crop either way), but on two loaded cores (load 10) a crop's words took a median
# 1.6 ms of wall time with one thread against 3.1 ms with two, waiting for both to be
# scheduled. Every image here is a crop or one frame; the processes (server, workers, ingest
# workers) are the parallelism.
cv2.setNumThreads(1)


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


def _inside(mask: np.ndarray | None, pixels: np.ndarray, side: int) -> np.ndarray | None:
    """The mask at `side` x `side` (None when there is none, it does not fit or is empty)."""
    if mask is None or mask.shape[:2] != pixels.shape[:2]:
        return None
    inside = cv2.resize((mask.reshape(mask.shape[:2]) > 0).astype(np.uint8), (side, side),
                        interpolation=cv2.INTER_NEAREST)
    return inside if inside.any() else None


def orb_features(pixels: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """The ORB descriptors (rows of 32 bytes) of a crop scaled to ORB_SIDE, keypoints on its
    mask when it has one."""
    grey = cv2.cvtColor(cv2.resize(_bgr(pixels), (ORB_SIDE, ORB_SIDE)), cv2.COLOR_BGR2GRAY)
    _, found = cv2.ORB_create(**ORB_PARAMETERS).detectAndCompute(
        grey, _inside(mask, pixels, ORB_SIDE))
    return np.zeros((0, 32), np.uint8) if found is None else found


@functools.cache
def _matcher() -> cv2.DescriptorMatcher:
    """One brute-force Hamming matcher (made anew, it cost twice the matching itself)."""
    return cv2.BFMatcher(cv2.NORM_HAMMING)


@functools.cache
def vocabulary() -> np.ndarray:
    """The visual words: ORB descriptors (rows of 32 bytes) each standing for its neighbours."""
    with np.load(VOCABULARY) as stored:
        return stored["words"]


def word_counts(pixels: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """How many of the crop's ORB keypoints fall on each visual word (nearest in Hamming
    distance): the crop's bag of words."""
    words = vocabulary()
    features = orb_features(pixels, mask)
    nearest = [m.trainIdx for m in _matcher().match(features, words)] if len(features) else []
    return np.bincount(np.asarray(nearest, np.int64), minlength=len(words)).astype(np.uint16)


def crop_descriptors(pixels: np.ndarray, mask: np.ndarray | None = None
                     ) -> dict[str, np.ndarray]:
    """What a crop looks like: `crop-colour`, a hue-saturation histogram of its (masked)
    pixels, `crop-hog`, the histogram of oriented gradients of its outline and print, and
    `crop-orb`, its bag of ORB visual words (as visual_words.VisualWords describes it)."""
    bgr = cv2.resize(_bgr(pixels), (SIDE, SIDE), interpolation=cv2.INTER_AREA)
    hsv = cv2.cvtColor(bgr, cv2.COLOR_BGR2HSV)
    colour = cv2.calcHist([hsv], [0, 1], _inside(mask, pixels, SIDE),
                          [HUE_BINS, SATURATION_BINS], [0, 180, 0, 256])
    gradients = gradient_histograms(cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY))
    found = {"crop-colour": sqrt_distribution(colour), "crop-hog": unit(gradients),
             ORB_DESCRIPTOR: sqrt_distribution(word_counts(pixels, mask))}
    return {name: vector for name, vector in found.items() if vector is not None}
