"""ORB visual words: a crop's local features as words of a fixed vocabulary, the descriptor that
similarity search (`crop-orb`) and the long-term catalogue (views of modality "visualwords")
share.

The vocabulary is fixed and ships with the package (`orb_vocabulary.npy`, 64 words of 32 bytes,
2 kB), not learnt from the stored crops: a word must mean the same thing for ever, since the
catalogue's models keep words as their nodes and the index keeps the vectors made of them (a
vocabulary learnt again would change every stored model and vector), and the first crop of a
new memory needs words before any crop is stored. It was learnt, seeded, from real images only,
none of the generated kitchen week that bench/similarity.py measures it on: 3,000 square
windows of the RoboSherlock kitchen frame and 100 of each product image of the shipped lookup
catalogue (which were cut from RoboSherlock frames), each scaled to 64 px as crops are, their
ORB features (appearance.py's parameters), 20,000 of them clustered by k-means on their bits
(OpenCV's, k-means++ seeds) and each centre's bits rounded. Made again by

    python -m percept_memory.memory.types.visual_words \\
        ../shared/data/robosherlock/samples/kitchen/rgb_*.png \\
        percept_memory/ingest/backends/products/*.jpg

Where they are computed: ORB costs ~0.1-0.3 ms a 64 px crop, a quarter to a half of what
storing a whole cluster costs (~0.45 ms at 2,200 clusters/s), so not at ingest: the index
computes them with the crop's other descriptors when it catches up (memory/similarity.py), and
the catalogue stage from the crop as it learns (catalogue/views.py). Both after the scene is
stored; neither stores them: the crop is kept, and the words are a function of it.
"""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np

from .annotations import Annotation
from .appearance import ORB_DESCRIPTOR, VOCABULARY, orb_features, sqrt_distribution, word_counts
from .base import stored_type
from .raw import NDArray

WORDS = 64
VIEWS = 3  # words a crop gives the catalogue: its most frequent
TRAINING_WINDOWS = 3000  # per frame; 100 per product image
TRAINING_FEATURES = 20_000
CROP = 64


@stored_type("pm.annotation.VisualWords")
class VisualWords(Annotation):
    """How many of a crop's ORB keypoints fall on each word of the shipped vocabulary (its bag
    of visual words). Computed from an ImageROI's crop by `of_crop`; an annotator may also send
    it."""

    counts: NDArray

    @classmethod
    def of_crop(cls, pixels: np.ndarray, mask: np.ndarray | None = None) -> VisualWords | None:
        """The crop's words (None when ORB finds no keypoint in it: a plain surface)."""
        counts = word_counts(pixels, mask)
        return cls(counts=counts, source="orb") if counts.any() else None

    def views(self) -> list[str]:
        """Its VIEWS most frequent words (ties: the lower word): a binary bag of views with
        few nodes, as the catalogue's other modalities give (Duceux 5.3.1)."""
        counts = np.asarray(self.counts, np.int64).ravel()
        ranked = np.lexsort((np.arange(len(counts)), -counts))[:VIEWS]
        return [str(word) for word in ranked if counts[word] > 0]

    def descriptors(self) -> dict[str, np.ndarray]:
        """Square roots of the word distribution: the inner product of two is the
        Bhattacharyya overlap of their bags of words."""
        vector = sqrt_distribution(self.counts)
        return {} if vector is None else {ORB_DESCRIPTOR: vector}


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


def learn_vocabulary(paths: list[Path], seed: int = 0) -> np.ndarray:
    """WORDS binary centres of the crops' ORB features (k-means on their bits, rounded)."""
    rng = np.random.default_rng(seed)
    features = np.concatenate([orb_features(c) for c in training_crops(paths, rng)])
    chosen = features[rng.permutation(len(features))[:TRAINING_FEATURES]]
    cv2.setRNGSeed(seed)
    criteria = (cv2.TERM_CRITERIA_MAX_ITER + cv2.TERM_CRITERIA_EPS, 30, 0.01)
    _, _, centres = cv2.kmeans(np.unpackbits(chosen, axis=1).astype(np.float32), WORDS, None,
                               criteria, 2, cv2.KMEANS_PP_CENTERS)
    return np.packbits(centres > 0.5, axis=1)


if __name__ == "__main__":
    if len(sys.argv) < 2:
        raise SystemExit("usage: python -m percept_memory.memory.types.visual_words IMAGE...")
    np.save(VOCABULARY, learn_vocabulary([Path(p) for p in sys.argv[1:]]))
    print(f"{WORDS} words written to {VOCABULARY}")
