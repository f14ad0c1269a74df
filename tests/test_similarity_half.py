"""The exact filtered search scans a float16 copy of the vectors and scores again in float32
the rows its rounding leaves in doubt (memory/similarity.py): it must find what the float32 scan
finds, on vectors close enough that float16 alone would not, and an index folder written before
the copy existed must load and search the same way."""

from __future__ import annotations

import numpy as np
import pytest
from bson import ObjectId

from percept_memory.memory import similarity
from percept_memory.memory.similarity import (
    Entry,
    RowFilter,
    SimilarityIndex,
    Vectors,
    in_half,
)

ROBOTS, REGIONS, MAPS = ["r0", "r1", "r2"], ["table", "shelf"], ["m0", "m1"]


def unit(rows: np.ndarray) -> np.ndarray:
    return (rows / np.linalg.norm(rows, axis=-1, keepdims=True)).astype(np.float32)


def crowded(rng: np.random.Generator, count: int, ndim: int) -> np.ndarray:
    """Unit vectors in a few tight bunches: within a bunch scores differ by less than float16
    can tell apart, so its ranking alone is wrong there."""
    centres = unit(rng.normal(size=(8, ndim)))
    return unit(centres[rng.integers(len(centres), size=count)]
                + rng.normal(scale=3e-4, size=(count, ndim)))


@pytest.fixture(scope="module")
def index(tmp_path_factory) -> SimilarityIndex:
    """3,000 clusters with two descriptors (one on every other cluster only), random robots,
    regions, maps and times, added in batches as a refresh adds them."""
    rng = np.random.default_rng(0)
    index = SimilarityIndex(None, tmp_path_factory.mktemp("half"))  # type: ignore[arg-type]
    a, b = crowded(rng, 3000, 144), crowded(rng, 3000, 32)
    for first in range(0, 3000, 700):
        index.add(Entry(ObjectId(), int(rng.integers(0, 1000)), ROBOTS[rng.integers(3)],
                        REGIONS[rng.integers(2)], MAPS[rng.integers(2)],
                        {"a": a[i], **({"b": b[i]} if i % 2 else {})})
                  for i in range(first, min(first + 700, 3000)))
    return index


def random_filters(rng: np.random.Generator, count: int) -> list[RowFilter]:
    filters = []
    for _ in range(count):
        after = int(rng.integers(0, 800))
        filters.append(RowFilter(
            robot=list(rng.choice(ROBOTS, int(rng.integers(0, 3)), replace=False)),
            region=list(rng.choice(REGIONS, int(rng.integers(0, 2)), replace=False)),
            map=list(rng.choice(MAPS, int(rng.integers(0, 2)), replace=False)),
            after=after, before=after + int(rng.integers(0, 1000))))
    return filters


def in_float32(monkeypatch) -> None:
    """The exact search as it was before the float16 copy: every passing row in float32."""
    monkeypatch.setattr(Vectors, "_rounding_bound", lambda *_: np.inf)


def test_float16_alone_would_rank_these_vectors_wrongly(index):
    vectors = index.vectors["a"]
    rows = np.arange(len(index.rows))
    wrong = 0
    for query in vectors.matrix[:20]:
        rough = vectors._half_scores(rows, in_half(query))
        exact = vectors.scores(rows, query)
        wrong += set(np.argsort(-rough)[:21]) != set(np.argsort(-exact)[:21])
    assert wrong >= 10


def test_the_float16_scan_finds_what_the_float32_scan_finds(index, monkeypatch):
    rng = np.random.default_rng(1)
    filters = random_filters(rng, 40)
    starts = [index.rows.ids[i] for i in rng.integers(len(index.rows), size=len(filters))]
    asked = [(index.descriptors_of(start), k, where, [start])
             for start, where, k in zip(starts, filters, rng.integers(1, 40, len(filters)),
                                        strict=True)]
    asked += [({"a": unit(rng.normal(size=144)), "b": unit(rng.normal(size=32))}, 10, where, [])
              for where in filters[:10]]
    found = [index.search(*question) for question in asked]
    assert sum(len(f) for f in found) > 10 * len(found)  # the filters let rows through
    with monkeypatch.context() as patched:
        in_float32(patched)
        assert [index.search(*question) for question in asked] == found


def test_the_rounding_bound_holds_at_every_scale_and_is_infinite_past_float16():
    rng = np.random.default_rng(2)
    for scale in (1e-7, 1e-3, 1.0, 300.0):  # subnormal float16 to near its largest products
        vectors = Vectors(64)
        stack = (rng.normal(size=(500, 64)) * scale).astype(np.float32)
        vectors.add(np.arange(500), stack)
        for query in (stack[0], stack[1] * 2, rng.normal(size=64).astype(np.float32)):
            rough = vectors._half_scores(np.arange(500), in_half(query))
            exact = vectors.scores(np.arange(500), query).astype(np.float64)
            bound = vectors._rounding_bound(query, in_half(query))
            assert np.isfinite(bound)
            assert np.abs(rough - exact).max() <= bound
    vectors.add(np.array([500]), np.full((1, 64), 1e5, np.float32))  # inf in float16
    assert vectors._rounding_bound(stack[0], in_half(stack[0])) == np.inf
    query = np.full(64, 1e5, np.float32)
    assert vectors._rounding_bound(query, in_half(query)) == np.inf
    assert 500 in vectors.best(np.arange(501), query, 3)  # still found: scanned in float32


def test_an_index_folder_from_before_the_float16_copy_loads_and_searches_the_same(index):
    index.save()
    assert sorted(p.name for p in index.folder.iterdir()) == sorted(
        [*(f"{base}{end}" for base in (similarity._file_name(n) for n in ("a", "b"))
           for end in (".npy", ".present.npy", ".usearch")), "rows.json", "rows.npz"])
    loaded = SimilarityIndex(None, index.folder)  # type: ignore[arg-type]
    loaded.load()
    for name, vectors in index.vectors.items():
        held = loaded.vectors[name]
        assert held.half.dtype == np.float16
        assert np.array_equal(held.half, held.matrix.astype(np.float16))
        assert held.reach == pytest.approx(vectors.reach)
    rng = np.random.default_rng(3)
    for where in random_filters(rng, 10):
        query = {"a": unit(rng.normal(size=144))}
        assert loaded.search(query, 10, where) == index.search(query, 10, where)


def summed_in_half(rows: np.ndarray, query: np.ndarray, out: np.ndarray) -> None:
    """Inner products summed in float16, as a kernel for a CPU with float16 arithmetic might."""
    total = np.zeros(len(rows), np.float16)
    for column in range(rows.shape[1]):
        total = (total + rows[:, column] * query[column]).astype(np.float16)
    out[:] = total


def test_a_numkong_summing_in_float16_is_found_out_and_not_relied_on(index, monkeypatch):
    rng = np.random.default_rng(4)
    asked = [({"a": index.vectors["a"].matrix[row]}, 10, where)
             for row, where in zip(rng.integers(len(index.rows), size=8), random_filters(rng, 8),
                                   strict=True)]
    with monkeypatch.context() as patched:
        in_float32(patched)
        expected = [index.search(*question) for question in asked]
    monkeypatch.setattr(similarity.numkong, "dot", summed_in_half)
    similarity.sums_in_float32.cache_clear()
    try:
        assert not similarity.sums_in_float32(144)
        assert [index.search(*question) for question in asked] == expected
        with monkeypatch.context() as trusted:
            trusted.setattr(similarity, "sums_in_float32", lambda ndim: True)
            assert [index.search(*question) for question in asked] != expected
    finally:
        similarity.sums_in_float32.cache_clear()


def test_of_rows_scoring_alike_the_first_added_are_found_whatever_the_scan_order(monkeypatch):
    rng = np.random.default_rng(5)
    looks = unit(rng.normal(size=(50, 16)))
    vectors = Vectors(16)
    vectors.add(np.arange(200), np.repeat(looks, 4, axis=0))  # each look stored 4 times
    query = looks[3]
    second = int(np.argsort(-(looks @ query))[1])  # the next look: 2 of its 4 rows are kept
    expected = {12, 13, 14, 15, 4 * second, 4 * second + 1}
    for shuffled in (np.arange(200), np.arange(200)[::-1], rng.permutation(200)):
        assert set(vectors.best(shuffled, query, 6).tolist()) == expected
        with monkeypatch.context() as patched:
            in_float32(patched)
            assert set(vectors.best(shuffled, query, 6).tolist()) == expected
