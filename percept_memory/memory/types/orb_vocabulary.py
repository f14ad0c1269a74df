"""How the shipped vocabulary of ORB visual words (orb_vocabulary.npz, visual_words.py says
why it is fixed) was made, and makes it again:

    python -m percept_memory.memory.types.orb_vocabulary IMAGE...

from real images only: square windows of each frame (many) or product picture (fewer) scaled
to crop size, their ORB features, k-means on the features' bits.
"""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np

from .appearance import VOCABULARY, orb_features

WORDS = 64
TRAINING_WINDOWS = 3000  # per frame; 100 per product image
TRAINING_FEATURES = 20_000
CROP = 64


def training_crops(paths: list[Path], rng: np.random.Generator) -> list[np.ndarray]:
    """Square windows of the images scaled to crop size: many of a frame, fewer of a product
    picture (one object)."""
    crops = []
    for path in paths:
        image = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if image is None:
            raise SystemExit(f"Error: {path} is not an image")
        height, width = image.shape[:2]
        frame = min(height, width) >= 4 * CROP
        for _ in range(TRAINING_WINDOWS if frame else 100):
            low = CROP * 3 // 4 if frame else min(height, width) // 2
            high = 200 if frame else min(height, width)
            side = int(rng.integers(low, high + 1))
            y, x = int(rng.integers(0, height - side + 1)), int(rng.integers(0, width - side + 1))
            crops.append(cv2.resize(image[y:y + side, x:x + side], (CROP, CROP),
                                    interpolation=cv2.INTER_AREA))
    return crops


def learn_vocabulary(paths: list[Path], seed: int = 0) -> dict[str, np.ndarray]:
    """WORDS binary centres of the crops' ORB features (k-means on their bits, rounded), and
    the share of all the features nearest each."""
    rng = np.random.default_rng(seed)
    features = np.concatenate([orb_features(c) for c in training_crops(paths, rng)])
    chosen = features[rng.permutation(len(features))[:TRAINING_FEATURES]]
    cv2.setRNGSeed(seed)
    criteria = (cv2.TERM_CRITERIA_MAX_ITER + cv2.TERM_CRITERIA_EPS, 30, 0.01)
    _, _, centres = cv2.kmeans(np.unpackbits(chosen, axis=1).astype(np.float32), WORDS, None,
                               criteria, 2, cv2.KMEANS_PP_CENTERS)
    words = np.packbits(centres > 0.5, axis=1)
    nearest = [m.trainIdx for m in cv2.BFMatcher(cv2.NORM_HAMMING).match(features, words)]
    counts = np.bincount(nearest, minlength=WORDS) + 1  # no word is never seen
    return {"words": words, "share": counts / counts.sum()}


if __name__ == "__main__":
    if len(sys.argv) < 2:
        raise SystemExit("usage: python -m percept_memory.memory.types.orb_vocabulary IMAGE...")
    np.savez(VOCABULARY, **learn_vocabulary([Path(p) for p in sys.argv[1:]]))
    print(f"{WORDS} words written to {VOCABULARY}")
