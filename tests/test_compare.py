"""The built-in types compare two lists at once (types/compare.py); each matrix entry must be
what comparing that one pair means: checked against the pair-by-pair definitions."""

from __future__ import annotations

import math

import numpy as np
import pytest

from percept_memory.memory.types import (
    Barcode,
    Classification,
    ImageROI,
    SemanticColor,
    Text,
)
from percept_memory.memory.types.hypotheses import PHASH_SIGMA_BITS

rng = np.random.default_rng(3)
WORDS = ["red", "Cup", "cup", "milk", "Milka", "500g", " tea "]


def _entries(matrix, a, b, pair):
    for i, x in enumerate(a):
        for j, y in enumerate(b):
            expected = pair(x, y)
            if expected is None:
                assert math.isnan(matrix[i, j]), (x, y)
            else:
                assert matrix[i, j] == pytest.approx(expected), (x, y)


def test_labels_match_by_their_words_case_and_spaces_aside():
    a = [Barcode(code=w) for w in WORDS]
    _entries(Barcode.similarities(a, a), a, a,
             lambda x, y: float(x.code.strip().casefold() == y.code.strip().casefold()))


def test_classifications_overlap_by_confidences_where_both_have_them_else_by_class():
    def make():
        confidences = dict(zip(["cup", "bowl", "plate"], rng.random(3).tolist(), strict=True))
        return Classification(class_name=str(rng.choice(["cup", "bowl"])),
                              confidences=confidences if rng.random() < 0.6 else {})

    def pair(x, y):
        if x.confidences and y.confidences:
            p, q = (np.array([d.get(k, 0) for k in ("bowl", "cup", "plate")]) for d in
                    (x.confidences, y.confidences))
            return min(1.0, float(np.sqrt(p / p.sum() * q / q.sum()).sum()))
        return float(x.class_name == y.class_name)

    a, b = [make() for _ in range(7)], [make() for _ in range(5)]
    _entries(Classification.similarities(a, b), a, b, pair)


def test_colours_share_the_smaller_part_of_each_name():
    a = [SemanticColor(ratios=dict(zip(rng.choice(["red", "blue", "white"], 2, replace=False),
                                       rng.dirichlet(np.ones(2)).tolist(), strict=True)))
         for _ in range(6)] + [SemanticColor(ratios={})]

    def pair(x, y):
        shared = x.ratios.keys() & y.ratios.keys()
        return sum(min(x.ratios[k], y.ratios[k]) for k in shared) if x.ratios and y.ratios \
            else None

    _entries(SemanticColor.similarities(a, a), a, a, pair)


def test_texts_compare_by_their_shared_words():
    a = [Text(text=" ".join(rng.choice(WORDS, 3))) for _ in range(6)] + [Text(text="--")]

    def pair(x, y):
        wx, wy = ({w.casefold() for w in t.text.replace("-", " ").split()} for t in (x, y))
        return len(wx & wy) / len(wx | wy) if wx and wy else None

    _entries(Text.similarities(a, a), a, a, pair)


def test_crops_compare_by_the_hamming_distance_of_their_hashes():
    a = [ImageROI(box=(0, 0, 1, 1), phash=f"{int(rng.integers(0, 2**63)) * 2 + 1:016x}")
         for _ in range(5)] + [ImageROI(box=(0, 0, 1, 1))]
    _entries(ImageROI.similarities(a, a), a, a, lambda x, y: None if not x.phash or not y.phash
             else math.exp(-(((int(x.phash, 16) ^ int(y.phash, 16)).bit_count()
                              / (2 * PHASH_SIGMA_BITS)) ** 2)))
