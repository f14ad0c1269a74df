"""The exact filtered search scans an int8 copy of the vectors and scores again in float32 the
rows its bound leaves in doubt (memory/similarity.py): it must find what the float32 scan finds,
on vectors close enough that int8 alone would not, on rows of any length (zero, tiny, with a huge
value), and an index folder written before the copy existed must load and search the same way."""

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
    quantised,
)

ROBOTS, REGIONS, MAPS = ["r0", "r1", "r2"], ["table", "shelf"], ["m0", "m1"]


def unit(rows: np.ndarray) -> np.ndarray:
    return (rows / np.linalg.norm(rows, axis=-1, keepdims=True)).astype(np.float32)


def crowded(rng: np.random.Generator, count: int, ndim: int) -> np.ndarray:
    """Unit vectors in a few tight bunches: within a bunch scores differ by less than int8
    can tell apart, so its ranking alone is wrong there."""
    centres = unit(rng.normal(size=(8, ndim)))
    return unit(centres[rng.integers(len(centres), size=count)]
                + rng.normal(scale=3e-4, size=(count, ndim)))


@pytest.fixture(scope="module")
def index(tmp_path_factory) -> SimilarityIndex:
    """3,000 clusters with two descriptors (one on every other cluster only), random robots,
    regions, maps and times, added in batches as a refresh adds them."""
    rng = np.random.default_rng(0)
    index = SimilarityIndex(None, tmp_path_factory.mktemp("int8"))  # type: ignore[arg-type]
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
    """The exact search as it was before the int8 copy: every passing row in float32."""
    monkeypatch.setattr(Vectors, "_rough_scores", lambda *_: None)


def float32_best(vectors: Vectors, rows: np.ndarray, query: np.ndarray, count: int,
                 monkeypatch) -> set[int]:
    with monkeypatch.context() as patched:
        in_float32(patched)
        return set(vectors.best(rows, query, count).tolist())


def test_int8_alone_would_rank_these_vectors_wrongly(index):
    vectors = index.vectors["a"]
    rows = np.arange(len(index.rows))
    wrong = 0
    for query in vectors.matrix[:20]:
        rough, _ = vectors._rough_scores(rows, query)
        exact = vectors.scores(rows, query)
        wrong += set(np.argsort(-rough)[:21]) != set(np.argsort(-exact)[:21])
    assert wrong >= 10


def test_the_int8_scan_finds_what_the_float32_scan_finds(index, monkeypatch):
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


def hard_rows(kind: str, rng: np.random.Generator) -> np.ndarray:
    """5,000 rows of 48 floats that are hard for int8 in one way each."""
    normal = rng.normal(size=(5000, 48)).astype(np.float32)
    if kind == "random":
        return normal
    if kind == "near ties":  # bunches closer than int8's steps, and exact duplicates
        rows = crowded(rng, 5000, 48)
        rows[1000:1400] = rows[:400]
        return rows
    if kind == "norms far apart":  # lengths from 1e-6 to 1e6
        return (normal * 10.0 ** rng.uniform(-6, 6, (5000, 1))).astype(np.float32)
    if kind == "a zero row":
        normal[7] = 0
        return normal
    if kind == "a huge value":  # its row's other values are all 0 in int8
        normal[11, 3] = 1e30
        return normal
    assert kind == "subnormal"  # below float32's normal numbers
    return (normal * 1e-40).astype(np.float32)


KINDS = ["random", "near ties", "norms far apart", "a zero row", "a huge value", "subnormal"]


@pytest.mark.parametrize("kind", KINDS)
def test_the_int8_scan_finds_the_float32_scans_rows_on_hard_data(kind, monkeypatch):
    monkeypatch.setattr(similarity, "SCAN_THREADS", 3)  # up to 3 blocks scanned at once
    rng = np.random.default_rng(KINDS.index(kind))
    stack = hard_rows(kind, rng)
    vectors = Vectors(48)
    vectors.add(np.arange(len(stack)), stack)
    queries = [stack[i] for i in rng.integers(len(stack), size=6)] + [
        rng.normal(size=48).astype(np.float32), -stack[7], np.zeros(48, np.float32)]
    pruned = 0
    for query in queries:
        for count in (1, 5, 21, 300):
            rows = rng.permutation(len(stack))[:int(rng.integers(count + 1, len(stack)))]
            assert vectors._rough_scores(rows, query) is not None  # int8 was used
            found = vectors.best(rows, query, count)
            assert len(found) == count
            assert set(found.tolist()) == float32_best(vectors, rows, query, count,
                                                       monkeypatch)
            rough, bound = vectors._rough_scores(rows, query)
            pruned += np.sum(rough + bound >= np.sort(rough - bound)[-count]) < len(rows) / 2
    if kind != "subnormal":  # there every float32 product is 0: nothing to tell apart
        assert pruned >= 10  # most rows were not scored again in float32


def test_a_zero_row_is_found_when_it_scores_best():
    rng = np.random.default_rng(6)
    stack = -np.abs(rng.normal(size=(500, 32))).astype(np.float32)  # every score below 0
    stack[123] = 0
    vectors = Vectors(32)
    vectors.add(np.arange(500), stack)
    query = np.abs(rng.normal(size=32)).astype(np.float32)
    assert vectors.best(np.arange(500), query, 1).tolist() == [123]
    assert 123 not in vectors.best(np.arange(500), -query, 10)


@pytest.mark.parametrize("scale", [1e-40, 1e-7, 1.0, 300.0, 1e15])
def test_the_bound_holds_for_every_row(scale):
    rng = np.random.default_rng(int(np.log10(scale)) + 50)
    for ndim in (1, 3, 64, 144):
        stack = (rng.normal(size=(500, ndim)) * scale
                 * 10.0 ** rng.uniform(-3, 0, (500, 1))).astype(np.float32)
        stack[0] = 0
        stack[1, 0] = 30 * scale  # one value far past the rest of its row
        vectors = Vectors(ndim)
        vectors.add(np.arange(500), stack)
        for query in (stack[2], stack[3] * 1000, rng.normal(size=ndim).astype(np.float32),
                      np.zeros(ndim, np.float32), rng.normal(size=ndim).astype(np.float32)
                      * np.float32(1e-38)):
            rough, bound = vectors._rough_scores(np.arange(500), query)
            exact = vectors.scores(np.arange(500), query).astype(np.float64)
            assert np.all(np.abs(rough - exact) <= bound)
            assert np.all(bound < np.abs(query).sum() * np.abs(stack).max(axis=1) + 1e-30)


def test_quantised_rows_are_within_half_a_step_and_fit_int8():
    rng = np.random.default_rng(7)
    rows = (rng.normal(size=(1000, 40)) * 10.0 ** rng.uniform(-44, 38, (1000, 1))).astype(
        np.float32)
    rows[0] = 0
    rows = rows[np.all(np.isfinite(rows), axis=1)]
    steps, sizes = quantised(rows)
    scales = sizes[:, :1]
    assert steps.dtype == np.int8 and np.abs(steps).max() == similarity.STEPS
    assert np.all(np.abs(rows - scales * steps) <= scales / 2 * (1 + 1e-12))
    assert scales[0] == 0 and not steps[0].any()
    assert np.allclose(sizes[:, 1], np.linalg.norm(rows.astype(np.float64), axis=1))


def test_past_float32_scores_are_not_bounded_and_scanned_in_float32():
    rng = np.random.default_rng(2)
    stack = rng.normal(size=(500, 64)).astype(np.float32)
    vectors = Vectors(64)
    vectors.add(np.arange(500), stack)
    vectors.add(np.array([500]), np.full((1, 64), 1e20, np.float32))  # scores past float32
    query = np.full(64, 1e20, np.float32)
    assert vectors._rough_scores(np.arange(501), query) is None
    assert vectors._rough_scores(np.arange(501), stack[0]) is not None
    assert 500 in vectors.best(np.arange(501), query, 3)  # still found: scanned in float32


def test_an_index_folder_from_before_the_int8_copy_loads_and_searches_the_same(index):
    index.save()
    assert sorted(p.name for p in index.folder.iterdir()) == sorted(
        [*(f"{base}{end}" for base in (similarity._file_name(n) for n in ("a", "b"))
           for end in (".npy", ".present.npy", ".usearch")), "rows.json", "rows.npz"])
    loaded = SimilarityIndex(None, index.folder)  # type: ignore[arg-type]
    loaded.load()
    for name, vectors in index.vectors.items():
        held = loaded.vectors[name]
        steps, sizes = quantised(held.matrix)
        assert np.array_equal(held.steps, steps) and np.array_equal(held.sizes, sizes)
        assert np.array_equal(held.sizes, vectors.sizes[:len(held.sizes)])
    rng = np.random.default_rng(3)
    for where in random_filters(rng, 10):
        query = {"a": unit(rng.normal(size=144))}
        assert loaded.search(query, 10, where) == index.search(query, 10, where)


def summed_in_int16(rows: np.ndarray, query: np.ndarray) -> np.ndarray:
    """Inner products wrapped to 16 bits, as a kernel summing in int16 would give them."""
    return (rows.astype(np.int64) @ query.T.astype(np.int64)).astype(np.int16)


def test_a_numkong_summing_in_16_bits_is_found_out_and_not_relied_on(index, monkeypatch):
    rng = np.random.default_rng(4)
    asked = [({"a": index.vectors["a"].matrix[row]}, 10, where)
             for row, where in zip(rng.integers(len(index.rows), size=8), random_filters(rng, 8),
                                   strict=True)]
    with monkeypatch.context() as patched:
        in_float32(patched)
        expected = [index.search(*question) for question in asked]
    monkeypatch.setattr(similarity.numkong, "dots_pack", np.asarray)
    monkeypatch.setattr(similarity.numkong, "dots_packed", summed_in_int16)
    similarity.dots_exact.cache_clear()
    try:
        assert not similarity.dots_exact(144)
        assert [index.search(*question) for question in asked] == expected
        with monkeypatch.context() as trusted:
            trusted.setattr(similarity, "dots_exact", lambda ndim: True)
            assert [index.search(*question) for question in asked] != expected
    finally:
        similarity.dots_exact.cache_clear()


def test_numkong_int8_sums_are_exact_here():
    """Else every exact search would scan float32: right, but slower than it should be."""
    assert similarity.dots_exact(144)
    assert not similarity.dots_exact(200_000)  # 127 * 127 * 200,000 is past int32


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


@pytest.mark.parametrize("layout_tail", [0, 700, similarity.LAYOUT_TAIL])
def test_rows_laid_out_added_since_and_removed_are_found_as_a_full_scan_finds_them(
        tmp_path, monkeypatch, layout_tail):
    """Searches between batches of rows added and removed, with the rows laid out again at
    every batch (0), at every other (700) or never (the default: 3,000 rows stay rows added since):
    the exact search finds the k best of a float64 scan of every row that passes."""
    monkeypatch.setattr(similarity, "LAYOUT_TAIL", layout_tail)
    rng = np.random.default_rng(6)
    index = SimilarityIndex(None, tmp_path)  # type: ignore[arg-type]
    rows = unit(rng.normal(size=(3000, 32)))
    entries: list[Entry] = []
    for first in range(0, 3000, 600):
        batch = [Entry(ObjectId(), int(rng.integers(0, 1000)), ROBOTS[rng.integers(3)],
                       REGIONS[rng.integers(2)], MAPS[rng.integers(2)],
                       {"a": rows[i]} if i % 5 else {})  # every fifth without the descriptor
                 for i in range(first, first + 600)]
        index.add(batch)
        entries += batch
        for row in rng.integers(len(entries), size=20):
            index.rows.remove(int(row))
            index.vectors["a"].remove(int(row))
        live = index.rows.columns["live"]
        for where in random_filters(rng, 8):
            query = unit(rng.normal(size=32))
            passing = [i for i, e in enumerate(entries) if live[i] and "a" in e.descriptors
                       and where.after <= e.time <= where.before
                       and all(getattr(e, key) in getattr(where, key)
                               for key in ("robot", "region", "map") if getattr(where, key))]
            expected = sorted(passing, key=lambda i: -float(rows[i].astype(np.float64)
                                                            @ query))[:7]
            found = index.search({"a": query}, 7, where)
            assert [m.cluster_id for m in found] == [entries[i].cluster_id for i in expected]
    laid = index.rows.layout.count
    assert laid == (3000 if layout_tail == 0 else 2400 if layout_tail == 700 else 0)
