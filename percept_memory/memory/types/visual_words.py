"""ORB visual words: a crop's local features as words of a fixed vocabulary, the `crop-orb`
descriptor of similarity search. Not views of the long-term catalogue: with a crop's two most
telling words as views, the kitchen week's catalogue held 27 entries for 20 objects instead of
26 (seed 0) and 27 instead of 22, one mixing two kinds (seed 1), and its stage took 2.4 times
the CPU (0.67 -> 1.58 ms a cluster): measured, not adopted.

The vocabulary is fixed and ships with the package (`orb_vocabulary.npz`: 64 words of 32 bytes
and the share of the training features on each, 3 kB), not learnt from the stored crops: a word
must mean the same thing for ever (the index keeps the vectors made of them, and vectors of two
vocabularies do not compare), and the first crop of a new memory needs words before any crop is
stored. It was learnt, seeded, from real images only, none of the generated kitchen week that
bench/similarity.py measures it on: 3,000 square windows of the RoboSherlock kitchen frame and
100 of each product image of the shipped lookup catalogue (cut from RoboSherlock frames), each
scaled to 64 px as crops are, their ORB features (appearance.py's parameters), 20,000 of them
clustered by k-means on their bits (OpenCV's, k-means++ seeds), each centre's bits rounded
(orb_vocabulary.py makes it again).

Where they are computed: ORB costs ~0.1-0.3 ms a 64 px crop, a quarter to a half of what
storing a whole cluster costs (~0.45 ms at 2,200 clusters/s), so not at ingest: the index
computes them with the crop's other descriptors when it catches up (memory/similarity.py),
after the scene is stored, and does not store them: the crop is kept, and the words are a
function of it.
"""

from __future__ import annotations

import numpy as np

from .annotations import Annotation
from .appearance import (
    ORB_DESCRIPTOR,
    sqrt_distribution,
    vocabulary,
    word_counts,
)
from .base import stored_type
from .raw import NDArray


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

    def words(self) -> np.ndarray | None:
        """The counts, when they are counts of the shipped vocabulary's words (an annotator
        counting on a vocabulary of its own says nothing comparable: None)."""
        counts = np.asarray(self.counts).ravel()
        if (counts.shape != (len(vocabulary()),) or counts.dtype.kind not in "iuf"
                or not np.all(np.isfinite(counts)) or np.any(counts < 0)):
            return None
        return counts.astype(np.float64)

    def descriptors(self) -> dict[str, np.ndarray]:
        """Square roots of the word distribution: the inner product of two is the
        Bhattacharyya overlap of their bags of words."""
        counts = self.words()
        vector = None if counts is None else sqrt_distribution(counts)
        return {} if vector is None else {ORB_DESCRIPTOR: vector}
