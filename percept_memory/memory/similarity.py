"""Vector indexes for similarity search ("find more like this"): one approximate-nearest-
neighbour index per descriptor (the named unit vectors types declare: types/appearance.py),
kept in a folder beside the database and derived from it (MongoDB is the source of truth).

Why usearch: of the well-kept ANN libraries on PyPI, usearch ships a 2.3 MB wheel for every
platform, saves and loads (or memory-maps) an index as one file, and removes and adds vectors
in place. hnswlib has no wheel (PyPI holds its source only: a C++ compiler at install time)
and filters through a Python callback per candidate; faiss-cpu is a 19 MB wheel whose HNSW
index cannot remove a vector. Filters need no help from the library: every cluster's time,
robot, region and map never change once stored, so the index keeps them as numpy arrays (a
row per cluster) and a filter selects rows. When at most EXACT_ROWS pass, those rows are
searched exactly, from the vectors kept a second time as a matrix by row (memory for speed:
a graph search has to fetch ~2k / (share passing) neighbours to keep k); else the graph's
neighbours are over-fetched and kept when they pass. The exact search scans an int8 copy of
the matrix (a scale per row; derived when loaded, never saved) and scores again in float32
only the rows its bound on the rounding leaves in doubt: its results are the float32 scan's,
at a quarter of the bytes fetched. That scan is bound by memory, so the int8 copy is kept in
the order of a layout of the rows, sorted by robot, map and time (a database-style clustered
index): a robot's or a map's time window is one range there, scanned as it lies, where the
same rows gathered from all over took 2.5x as long. Rows added since the layout are scanned
from the copy by row until there are enough of them to lay the rows out again.

Kept current from a watermark, not a pipeline stage: the folder is local to each process
(`pmem serve`, `pmem query`) while MongoDB may be shared, so each process's index catches up
by itself before it answers (`refresh`): it reads the ids of the clusters stored since it last
read them (ids newer than that time less a margin: ids come from the storing clients' clocks,
before their transactions commit) and adds those it lacks. Not since the newest id it holds:
after a burst of ingest, every query would read the burst's last margin of ids again (22,000 at
2,200 clusters/s) until the next cluster is stored. When the count of clusters still differs
(ids older than the margin, clusters removed) it compares every id with MongoDB's and adds or
removes the difference. Storing a scene does
no index work at all: the first query after a burst of ingest pays for it, or, in a server, the
keeper's thread does, at a lower CPU priority (index_keeper.py). Searches go on while a catch-up
reads and describes clusters: the index is held only to add them, a chunk at a time.
"""

from __future__ import annotations

import functools
import json
import logging
import os
import re
import threading
import zlib
from collections.abc import Iterable, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from pathlib import Path
from zipfile import BadZipFile

import numkong
import numpy as np
from bson import ObjectId
from usearch.index import Index

from percept_memory.converters.registry import aliases_of, name_of, registered_types

from .schema import CLUSTERS, SCENES
from .settings import Settings
from .store import MemoryStore
from .types import Annotation, Hypothesis

log = logging.getLogger(__name__)

FORMAT = 2  # of the folder's files: another number means rebuild
# How long before a refresh read them a cluster's id may have been made and still not be
# committed (ids come from the clock of the client that stored it, before its transaction
# commits). Later ones are found by the count check; a wider margin costs every refresh the ids
# stored in it.
MARGIN = timedelta(seconds=10)
EXPANSION_SEARCH = 128  # usearch's default 64 finds half the true 10 nearest of random data
CHUNK = 100  # clusters read and described, then added, at a time (~0.15 s of CPU)
PROGRESS_EVERY = 500  # chunks: a build from a large database logs how far it is
# When a filter passes at most this many rows they are searched exactly. Exact is always right,
# a filtered graph search is not: the nearest rows passing a narrow filter are often far, where
# the graph finds few of them (a robot and a day, 7 % of a million rows: the true top 10 for 1
# query of 150); so exact as long as it stays cheap: its cost is the rows', ~0.03 us each.
EXACT_ROWS = 100_000
SCORE_BLOCK = 2048  # rows gathered and scored at a time (~1 MB of 144 floats: in the cache)
# The rows are laid out again (Rows.passing) when more than this many, or an eighth of those
# laid out, were added since.
LAYOUT_TAIL = 4096
SCAN_THREADS = os.cpu_count() or 1  # a filter's rows are scanned in this many parts at once
QUANTISE_BLOCK = 65_536  # rows made int8 at a time when loaded (each a float64 row meanwhile)
STEPS = 127  # int8 steps each side of zero: a row's largest |value| is 127 of its scale
FLOAT32_EPS = float(np.finfo(np.float32).eps)  # per term, bounds a float32 sum's own error
FLOAT32_TINY = float(np.finfo(np.float32).smallest_subnormal)  # bounds a product's underflow
FLOAT32_MAX = float(np.finfo(np.float32).max)
# The bound's share for float64's own rounding (of the int8 scores, the bounds, their sums):
# ~2^-52 of |q| |x|, where a row's bound is at least ndim * FLOAT32_EPS (2^-23) of it.
SLACK = 2.0**-20
# The files are written again when the rows added or removed since are SAVE_EVERY and an
# SAVE_SHARE-th of those held: writing a million rows' files (1.3 GB) takes ~2 s, searches wait
# meanwhile, and a thousand clusters are stored in about a second.
SAVE_EVERY = 1000
SAVE_SHARE = 8
META = ("time", "robot", "region", "map")  # per row; robot, region and map as codes
COLUMNS = {"live": bool, "time": np.int64, "robot": np.int32, "region": np.int32,
           "map": np.int32}


@dataclass
class Match:
    """One cluster found: its id and how alike it is per descriptor (cosine, clipped to
    0..1), and over all the descriptors both have (their mean)."""

    cluster_id: ObjectId
    similarity: float
    descriptors: dict[str, float]


@dataclass
class Entry:
    """A cluster to index: what filters read of it, and its descriptors."""

    cluster_id: ObjectId
    time: int
    robot: str | None
    region: str | None
    map: str | None
    descriptors: Mapping[str, np.ndarray]

    def vectors(self) -> dict[str, np.ndarray]:
        """Its descriptors that can be indexed (those with a value not finite are left out)."""
        return {name: vector for name, vector in self.descriptors.items()
                if np.all(np.isfinite(vector))}


@dataclass(frozen=True)
class RowFilter:
    """Which clusters may be found: any of these robots, regions and maps, in a time window
    (nanoseconds, both ends included). Empty means any."""

    robot: Sequence[str] = ()
    region: Sequence[str] = ()
    map: Sequence[str] = ()
    after: int | None = None
    before: int | None = None

    def narrows(self) -> bool:
        return bool(self.robot or self.region or self.map) or \
            self.after is not None or self.before is not None


class Rows:
    """The clusters the index knows, one row each, in the order they were added: the row is
    the key of the cluster's vectors in every descriptor's index. Columns are numpy arrays
    (grown by doubling), so a filter is a few vector operations."""

    def __init__(self, ids: Sequence[ObjectId] = (), columns: Mapping[str, np.ndarray] | None
                 = None, names: Mapping[str, list] | None = None):
        self.ids = list(ids)
        self.row_of = {oid: row for row, oid in enumerate(self.ids)}
        self.newest = max(self.ids, default=None)
        self.names = {key: list((names or {}).get(key, [])) for key in META[1:]}
        self._code_of = {k: {n: i for i, n in enumerate(v)} for k, v in self.names.items()}
        given = columns or {}
        self.columns = {key: np.array(given.get(key, []), dtype=dtype)
                        for key, dtype in COLUMNS.items()}
        self._live = int(self.columns["live"].sum())
        self.layout = Layout.of(self, 0)  # no row laid out yet: see passing

    def __len__(self) -> int:
        return len(self.ids)

    def holds(self, cluster_id: ObjectId) -> bool:
        """Whether the cluster has a row still in the database (one removed and stored again
        gets a new row)."""
        row = self.row_of.get(cluster_id)
        return row is not None and bool(self.columns["live"][row])

    def live_count(self) -> int:
        return self._live

    def remove(self, row: int) -> None:
        """The cluster left the database (its row stays: rows are keys in the graphs)."""
        if self.columns["live"][row]:
            self.columns["live"][row] = False
            self._live -= 1
            self.layout.remove(row)

    def add(self, cluster_id: ObjectId, time: int, values: Mapping[str, str | None]) -> int:
        row = len(self.ids)
        if row == len(self.columns["live"]):
            for key, column in self.columns.items():
                self.columns[key] = np.resize(column, max(16, 2 * row))
        self.columns["live"][row] = True
        self._live += 1
        self.columns["time"][row] = time
        for key, codes in self._code_of.items():
            if values[key] not in codes:
                codes[values[key]] = len(self.names[key])
                self.names[key].append(values[key])
            self.columns[key][row] = codes[values[key]]
        self.ids.append(cluster_id)
        self.row_of[cluster_id] = row
        self.newest = cluster_id if self.newest is None else max(self.newest, cluster_id)
        return row

    def passing(self, f: RowFilter) -> Selection:
        """The rows that pass the filter (and are still in the database): the laid-out rows
        as ranges of their layout, the rows added since as rows. The rows are laid out again
        when those added since are more than an eighth of those laid out (LAYOUT_TAIL at
        least), by the filtered query that finds them: ~0.2 s for a million rows of one
        descriptor, once per 125,000 rows added to them."""
        n = len(self)
        if n - self.layout.count > max(LAYOUT_TAIL, self.layout.count // 8):
            self.layout = Layout.of(self, n)
        tail, codes = slice(self.layout.count, n), self._codes(f)
        keep = self.columns["live"][tail].copy()  # (a view: &= would write into it)
        for key, wanted in codes.items():
            keep &= matching(self.columns[key][tail], wanted)
        times = self.columns["time"][tail]
        if f.after is not None:
            keep &= times >= f.after
        if f.before is not None:
            keep &= times <= f.before
        return Selection(self.layout, self.layout.ranges(f, codes),
                         tail.start + np.flatnonzero(keep))

    def _codes(self, f: RowFilter) -> dict[str, set[int]]:
        """The codes of the filter's robots, regions and maps (those it names)."""
        return {key: {self._code_of[key][v] for v in getattr(f, key) if v in self._code_of[key]}
                for key in META[1:] if getattr(f, key)}

    def save(self, folder: Path) -> None:
        """Write the rows in one file (ids, columns and the names the codes stand for)."""
        n = len(self)
        ids = np.frombuffer(b"".join(i.binary for i in self.ids), np.uint8).reshape(-1, 12)
        np.savez(folder / "rows.npz", ids=ids, names=np.array(json.dumps(self.names)),
                 **{key: column[:n] for key, column in self.columns.items()})

    @classmethod
    def load(cls, folder: Path) -> Rows:
        with np.load(folder / "rows.npz") as data:
            return cls([ObjectId(row.tobytes()) for row in data["ids"]],
                       {key: data[key] for key in COLUMNS}, json.loads(str(data["names"])))


class Layout:
    """The first `count` rows, those still in the database when laid out, sorted by robot,
    map and time (a position each). A filter's rows are then a range of positions per (robot,
    map) pair it lets through, its time window's, and the vectors' copies in this order
    (Vectors.laid) are scanned there as they lie: a robot's day of a million rows (73,000)
    in ~1 ms, where gathering the same rows from all over memory took ~2.5 ms."""

    def __init__(self, count: int, order: np.ndarray, columns: Mapping[str, np.ndarray]):
        self.count = count
        self.order = order  # position -> row
        self.columns = columns  # time, robot, region and map, by position
        self.position = np.full(count, -1, np.int64)  # row -> position (-1: not laid out)
        self.position[order] = np.arange(len(order))
        self.live = np.ones(len(order), bool)  # by position: rows removed since are not
        self.removed = 0
        robot, map_ = columns["robot"], columns["map"]
        edges = np.flatnonzero((robot[1:] != robot[:-1]) | (map_[1:] != map_[:-1])) + 1
        bounds = np.concatenate([[0], edges, [len(order)]]) if len(order) else np.zeros(1, int)
        self.groups = [(int(robot[begin]), int(map_[begin]), int(begin), int(end))
                       for begin, end in zip(bounds[:-1], bounds[1:], strict=True)]

    @classmethod
    def of(cls, rows: Rows, count: int) -> Layout:
        """The layout of the rows' first `count` rows."""
        live = np.flatnonzero(rows.columns["live"][:count])
        order = live[np.lexsort(tuple(rows.columns[key][live]
                                      for key in ("time", "map", "robot")))]
        return cls(count, order, {key: rows.columns[key][order] for key in META})

    def remove(self, row: int) -> None:
        position = int(self.position[row]) if row < self.count else -1
        if position >= 0 and self.live[position]:
            self.live[position] = False
            self.removed += 1

    def ranges(self, f: RowFilter, codes: Mapping[str, set[int]]
               ) -> list[tuple[int, int, np.ndarray | None]]:
        """The filter's rows (given the codes of the names it asks for): per (robot, map) pair
        it lets through, the positions of its time window, and which of them pass (None: all):
        those of its regions and not removed since."""
        found = []
        for robot, map_, begin, end in self.groups:
            if robot not in codes.get("robot", {robot}) or map_ not in codes.get("map", {map_}):
                continue
            times = self.columns["time"][begin:end]
            first = begin + (0 if f.after is None else
                             int(np.searchsorted(times, f.after, "left")))
            last = end if f.before is None else begin + int(np.searchsorted(times, f.before,
                                                                            "right"))
            if first >= last:
                continue
            mask = None
            if "region" in codes:
                mask = matching(self.columns["region"][first:last], codes["region"])
            if self.removed:
                live = self.live[first:last]
                mask = live if mask is None else mask & live
            found.append((first, last, mask))
        return found


@dataclass
class Selection:
    """The rows that pass a filter: ranges of a layout's positions (begin, end, and a mask
    of those that pass or None: all) and rows added since it was made (`added`)."""

    layout: Layout
    ranges: list[tuple[int, int, np.ndarray | None]]
    added: np.ndarray

    def __len__(self) -> int:
        return self.size

    @functools.cached_property
    def size(self) -> int:
        return len(self.added) + sum(end - begin if mask is None else int(mask.sum())
                                     for begin, end, mask in self.ranges)

    def rows(self) -> np.ndarray:
        """The rows, in no set order."""
        order = self.layout.order
        return np.concatenate([*(order[begin:end] if mask is None else order[begin:end][mask]
                                 for begin, end, mask in self.ranges), self.added])


def matching(column: np.ndarray, codes: set[int]) -> np.ndarray:
    """Which of the column's values are one of the codes (a comparison per code: faster than
    gathering by code)."""
    found = np.zeros(len(column), bool)
    for code in codes:
        found |= column == code
    return found


@dataclass
class Laid:
    """A descriptor's int8 rows, their sizes (scale, norm) and whether each row has the
    descriptor, in a layout's order; `whole`: all of them have it."""

    layout: Layout
    steps: np.ndarray
    sizes: np.ndarray
    present: np.ndarray
    whole: bool


class Vectors:
    """One descriptor's vectors, four times: in an HNSW graph (usearch) for the nearest among
    many rows; as a matrix by row for exact scores of a few (a filter's rows, the candidates):
    gathering and multiplying 36,000 rows of a million takes a few milliseconds, fetching as
    many neighbours from the graph ten times that; and that matrix in int8 (a scale per row),
    for a filter's rows, twice: by row, for the rows added since the rows were laid out, and in
    the layout's order (`laid`), where a filter's rows lie in a few ranges: the exact search
    scans those as they lie, int8 rows are a quarter of the bytes with integer products. The
    int8 copies are derived from the float32 matrix, not saved."""

    def __init__(self, ndim: int, index: Index | None = None, matrix: np.ndarray | None = None,
                 present: np.ndarray | None = None):
        self.index = index or Index(ndim=ndim, metric="ip", dtype="f32",
                                    expansion_search=EXPANSION_SEARCH)
        self.index.expansion_search = EXPANSION_SEARCH
        self.matrix = np.zeros((0, ndim), np.float32) if matrix is None else matrix
        self.present = np.zeros(0, bool) if present is None else present
        self.steps = np.empty(self.matrix.shape, np.int8)  # a row ~ its scale * its steps
        self.sizes = np.empty((len(self.matrix), 2))  # per row: its scale, its norm
        for start in range(0, len(self.matrix), QUANTISE_BLOCK):
            block = slice(start, start + QUANTISE_BLOCK)
            self.steps[block], self.sizes[block] = quantised(self.matrix[block])
        self.reach = float(self.sizes[:, 1].max(initial=0))  # the longest vector's norm
        self._laid: Laid | None = None  # the int8 copy in a layout's order

    @property
    def ndim(self) -> int:
        return self.matrix.shape[1]

    def add(self, rows: np.ndarray, stack: np.ndarray) -> None:
        self._room(int(rows.max()) + 1)
        self.matrix[rows] = stack
        self.steps[rows], self.sizes[rows] = quantised(stack)
        self.reach = max(self.reach, float(self.sizes[rows, 1].max()))
        self.present[rows] = True
        self.index.add(rows.astype(np.uint64), stack)

    def _room(self, rows: int) -> None:
        """Room for this many rows (those past the rows given so far: not present)."""
        held = len(self.present)
        if rows > held:
            size = max(16, 2 * held, rows)
            self.matrix = np.resize(self.matrix, (size, self.ndim))
            self.steps = np.resize(self.steps, (size, self.ndim))
            self.sizes = np.resize(self.sizes, (size, 2))
            self.present = np.resize(self.present, size)
            self.present[held:] = False

    def remove(self, row: int) -> None:
        if self.has(np.array([row]))[0]:
            self.present[row] = False
            self.index.remove(row)  # (the layout's ranges leave a removed row out)

    def laid(self, layout: Layout) -> Laid:
        """The int8 rows in the layout's order (gathered when the rows are laid out again:
        ~0.2 s a million)."""
        if self._laid is None or self._laid.layout is not layout:
            self._room(int(layout.order.max(initial=-1)) + 1)
            present = self.present[layout.order]
            self._laid = Laid(layout, np.take(self.steps, layout.order, axis=0),
                              np.take(self.sizes, layout.order, axis=0), present,
                              bool(present.all()))
        return self._laid

    def has(self, rows: np.ndarray) -> np.ndarray:
        """Which of the rows have this descriptor (none past the last row it was given)."""
        if len(rows) and rows.max() < len(self.present):
            return self.present[rows]  # one gather: a third of the masked one's time below
        inside = rows < len(self.present)
        out = np.zeros(len(rows), bool)
        out[inside] = self.present[rows[inside]]
        return out

    def scores(self, rows: np.ndarray, vector: np.ndarray) -> np.ndarray:
        """The rows' inner products with the vector, a block of rows at a time: a block
        gathered stays in the cache while it is multiplied, where gathering 36,000 rows
        whole writes 20 MB out and reads it back; and einsum is one thread, where BLAS's
        threads wait on each other on a busy machine (a 35,000-row product at load 7: 15 ms
        on BLAS's threads, 1.4 ms on one)."""
        out = np.empty(len(rows), np.float32)
        for start in range(0, len(rows), SCORE_BLOCK):
            block = rows[start:start + SCORE_BLOCK]
            out[start:start + len(block)] = np.einsum("ij,j->i", self.matrix[block], vector)
        return out

    def best(self, rows: np.ndarray, vector: np.ndarray, count: int) -> np.ndarray:
        """The `count` rows (of these, which must have this descriptor) that score highest in
        float32, in no order; of rows scoring as the count-th does, the first added. The int8
        copy is scanned; a row whose int8 score could, within its bound, reach the count-th
        best's lowest possible score may be among them, and only those rows are scored again in
        float32: the rows found are the float32 scan's, whatever order the rows come in."""
        return self._best(rows, vector, count)

    def best_of(self, selection: Selection, vector: np.ndarray, count: int) -> np.ndarray:
        """best() of a filter's rows that have this descriptor: a range whose rows all pass
        is scanned in the layout's copy as it lies; of a range with a mask (regions, rows
        removed, rows without the descriptor) the rows that pass are gathered from there
        (scanning the whole range and leaving out the rest was slower even when half pass:
        ~20 ns a row scanned, ~40 a row gathered, plus the masking)."""
        laid = self.laid(selection.layout)
        spans, rows = [], []
        for begin, end, mask in selection.ranges:
            if not laid.whole:
                have = laid.present[begin:end]
                mask = have if mask is None else mask & have
            positions = selection.layout.order[begin:end]
            if mask is None:
                spans.append((laid.steps, laid.sizes, slice(begin, end)))
                rows.append(positions)
            else:
                picked = np.flatnonzero(mask)
                spans.append((laid.steps, laid.sizes, begin + picked))
                rows.append(positions[picked])
        added = selection.added[self.has(selection.added)]
        spans.append((self.steps, self.sizes, added))
        return self._best(np.concatenate([*rows, added]), vector, count, spans)

    def _best(self, rows: np.ndarray, vector: np.ndarray, count: int,
              spans: list[tuple] | None = None) -> np.ndarray:
        """best(), the rows' int8 copies where the spans say (see _rough_scores)."""
        rough = self._rough_scores(rows, vector, spans) if len(rows) > count else None
        if rough is not None:
            scores, bounds = rough
            rows = rows[scores + bounds >= _kth_largest(scores - bounds, count)]
        if len(rows) <= count:
            return rows
        scores = self.scores(rows, vector)
        kth = _kth_largest(scores, count)
        above = rows[scores > kth]
        return np.concatenate([above, np.sort(rows[scores == kth])[:count - len(above)]])

    def _rough_scores(self, rows: np.ndarray, vector: np.ndarray,
                      spans: list[tuple] | None = None) -> tuple[np.ndarray, np.ndarray] | None:
        """The rows' int8 scores with the vector quantised alike, and how far each may be
        from its float32 score; None when that cannot be bounded (numkong's int8 sums not
        exact here, or float32 sums that may overflow: then the scan stays float32).
        `spans` say where the rows' int8 copies are, in the rows' order (default: the copy by
        row): each (int8 rows, their sizes, which: a slice or positions). Slices are scanned
        as they lie, positions gathered by np.take (fancy indexing copies int8 rows a value at
        a time, 2x slower), a block at a time by this thread and the scanners.
        With x ~ s x8 (each value within s/2) and q ~ t q8, the int8 score is s t (q8.x8),
        exact in int32, and |q.x - s t q8.x8| <= |q|_1 s/2 + |q - t q8| (|x| + sqrt(ndim)
        s/2); float32's own sum is within ndim eps |q| |x| (+ underflow) of q.x."""
        query = vector.astype(np.float64)
        length = float(np.linalg.norm(query))
        if not dots_exact(self.ndim) or not length * self.reach < FLOAT32_MAX / 2:
            return None
        steps, (scale, _) = quantised(query)
        packed = numkong.dots_pack(steps[None])
        scores, sizes = np.empty(len(rows)), np.empty((len(rows), 2))
        blocks, at = [], 0
        for copy, copy_sizes, which in spans or [(self.steps, self.sizes, rows)]:
            whole = isinstance(which, slice)
            size = which.stop - which.start if whole else len(which)
            for start in range(0, size, SCORE_BLOCK):
                end = min(size, start + SCORE_BLOCK)
                part = slice(which.start + start, which.start + end) if whole else \
                    which[start:end]
                blocks.append((copy, copy_sizes, part, at))
                at += end - start

        def scan(todo: list[tuple]) -> None:
            for copy, copy_sizes, part, at in todo:
                whole = isinstance(part, slice)
                block = copy[part] if whole else np.take(copy, part, axis=0)
                found = numkong.dots_packed(block, packed)  # int32, (rows, 1)
                scores[at:at + len(block)] = np.asarray(found)[:, 0]
                sizes[at:at + len(block)] = copy_sizes[part] if whole else \
                    np.take(copy_sizes, part, axis=0)

        share = max(1, min(SCAN_THREADS, len(blocks)))  # every share-th block to a thread
        helped = [scanners().submit(scan, blocks[i::share]) for i in range(1, share)]
        scan(blocks[::share])
        for part in helped:
            part.result()
        scales, norms = sizes[:, 0], sizes[:, 1]
        scores *= scales * scale
        missed = float(np.linalg.norm(query - scale * steps))
        grown = 1 + SLACK  # each term grown, not their sum: a pass over the rows less
        per_scale = (np.abs(query).sum() / 2 + missed * np.sqrt(self.ndim) / 2) * grown
        per_norm = (missed + self.ndim * FLOAT32_EPS * length) * grown
        return scores, per_scale * scales + per_norm * norms + self.ndim * FLOAT32_TINY * grown

    def nearest(self, vector: np.ndarray, count: int) -> np.ndarray:
        return self.index.search(vector, min(count, len(self.index))).keys.astype(np.int64)

    def save(self, folder: Path, name: str, rows: int) -> str:
        """Write the index and the first `rows` rows (beyond them: room to grow)."""
        base = _file_name(name)
        self.index.save(str(folder / f"{base}.usearch"))
        np.save(folder / f"{base}.npy", self.matrix[:rows])
        np.save(folder / f"{base}.present.npy", self.present[:rows])
        return base

    @classmethod
    def load(cls, folder: Path, base: str) -> Vectors:
        index = Index.restore(str(folder / f"{base}.usearch"))
        if index is None:
            raise ValueError(f"{base}.usearch is missing")
        matrix = np.load(folder / f"{base}.npy")
        return cls(matrix.shape[1], index, matrix, np.load(folder / f"{base}.present.npy"))


class SimilarityIndex:
    """The descriptor indexes of one database, in `folder`. Thread-safe."""

    def __init__(self, store: MemoryStore, folder: Path):
        self.store = store
        self.folder = folder
        self.lock = threading.RLock()  # held to change the rows and vectors, or search them
        self.upkeep = threading.Lock()  # one catch-up at a time
        self.rows = Rows()
        self.vectors: dict[str, Vectors] = {}
        self.unsaved = 0
        self._loaded = False
        self._read_at: datetime | None = None  # when the last refresh read the new ids

    @classmethod
    def of(cls, store: MemoryStore, settings: Settings) -> SimilarityIndex:
        """The index of the settings' database, under the data directory."""
        return cls(store, Path(settings.data_dir) / "similarity" / settings.db)

    # --- keeping it current ----------------------------------------------------------------

    def refresh(self) -> int:
        """Catch up with MongoDB (see the module's docstring): returns the rows changed. Two
        round trips (the new ids, the count), not one: asking both in one aggregate (the ids
        $unionWith a $collStats count) crashed mongod 6.0.5 when the union ran in a getMore
        (a segfault serialising the union's pipeline), and would have saved ~0.3 ms."""
        with self.upkeep:
            if not self._loaded:
                with self.lock:
                    self.load()
            changed = self._add(self._recent_unknown())
            if self.stored() != self.rows.live_count():
                changed += self._reconcile()
            with self.lock:
                self.unsaved += changed
                if self.unsaved >= max(SAVE_EVERY, len(self.rows) // SAVE_SHARE) or (
                        self.unsaved and not self._saved_once()):
                    self.save()
            return changed

    def behind(self) -> int:
        """How many stored clusters the index lacks (from MongoDB's count of them)."""
        return max(0, self.stored() - self.rows.live_count())

    def stored(self) -> int:
        """How many clusters MongoDB holds (its collection's count: no scan)."""
        return self.store.db[CLUSTERS].estimated_document_count()

    def _recent_unknown(self) -> list[ObjectId]:
        """The clusters stored since the last read (since the newest id held, after a load),
        less the margin, that the index lacks."""
        since = self._read_at or (self.rows.newest and self.rows.newest.generation_time)
        self._read_at = datetime.now(UTC)
        query = {} if since is None else {"_id": {"$gte": ObjectId.from_datetime(
            since - MARGIN)}}
        return [i for i in self._ids(query) if not self.rows.holds(i)]

    def _ids(self, query: dict) -> list[ObjectId]:
        return [d["_id"] for d in self.store.db[CLUSTERS].find(query, {"_id": 1}).sort("_id")]

    def _reconcile(self) -> int:
        stored = set(self._ids({}))
        live = self.rows.columns["live"]
        gone = [row for row, oid in enumerate(self.rows.ids) if live[row] and oid not in stored]
        with self.lock:
            for row in gone:
                self.rows.remove(row)
                for vectors in self.vectors.values():
                    vectors.remove(row)
        missing = sorted(i for i in stored if not self.rows.holds(i))
        log.info("similarity: %d clusters missing from the index, %d gone", len(missing),
                 len(gone))
        return len(gone) + self._add(missing)

    def _add(self, cluster_ids: Sequence[ObjectId]) -> int:
        """Read and describe these clusters, a chunk at a time, and add them."""
        for start in range(0, len(cluster_ids), CHUNK):
            chunk = cluster_ids[start:start + CHUNK]
            self.add(self.described(chunk))
            if start // CHUNK % PROGRESS_EVERY == PROGRESS_EVERY - 1:
                log.info("similarity: %d of %d clusters indexed", start + len(chunk),
                         len(cluster_ids))
        return len(cluster_ids)

    def described(self, cluster_ids: Sequence[ObjectId]) -> list[Entry]:
        """These clusters (those stored) read from MongoDB and described, without holding the
        index: searches go on meanwhile."""
        clusters = self.store.get_clusters(cluster_ids, described_kinds())
        meta = {d["_id"]: d for d in self.store.db[CLUSTERS].find(
            {"_id": {"$in": list(cluster_ids)}},
            {"scene_id": 1, "search.time": 1, "search.robot": 1, "search.region": 1})}
        maps = {d["_id"]: d.get("map") for d in self.store.db[SCENES].find(
            {"_id": {"$in": [d.get("scene_id") for d in meta.values()]}}, {"map": 1})}
        return [Entry(cluster_id, search.get("time", 0), search.get("robot"),
                      search.get("region"), maps.get(meta[cluster_id].get("scene_id")),
                      cluster.descriptors())
                for cluster_id, cluster in clusters.items()
                for search in [meta[cluster_id].get("search", {})]]

    def add(self, entries: Iterable[Entry]) -> None:
        """Add clusters with their descriptors (non-finite vectors are left out)."""
        with self.lock:
            self._loaded = True
            vectors: dict[str, tuple[list[int], list[np.ndarray]]] = {}
            for entry in entries:
                row = self.rows.add(entry.cluster_id, entry.time, {
                    "robot": entry.robot, "region": entry.region, "map": entry.map})
                for name, vector in entry.vectors().items():
                    keys, stack = vectors.setdefault(name, ([], []))
                    keys.append(row)
                    stack.append(vector)
            for name, (keys, stack) in vectors.items():
                if name not in self.vectors:
                    self.vectors[name] = Vectors(stack[0].size)
                self.vectors[name].add(np.array(keys), np.stack(stack).astype(np.float32))

    # --- files -----------------------------------------------------------------------------

    def _state_path(self) -> Path:
        return self.folder / "rows.json"

    def _saved_once(self) -> bool:
        return self._state_path().exists()

    def save(self) -> None:
        """Write the vectors, then the rows, then the state file naming the vectors' files
        (load checks that no vectors belong to rows that were not written)."""
        with self.lock:
            self.folder.mkdir(parents=True, exist_ok=True)
            files = {name: vectors.save(self.folder, name, len(self.rows))
                     for name, vectors in self.vectors.items()}
            self.rows.save(self.folder)
            state = {"format": FORMAT, "files": files}
            temporary = self._state_path().with_suffix(".tmp")
            temporary.write_text(json.dumps(state))
            temporary.replace(self._state_path())
            self.unsaved = 0

    def load(self) -> None:
        """Read the folder's files, if they are whole and of this format."""
        self._loaded = True
        try:
            state = json.loads(self._state_path().read_text())
            if state.get("format") != FORMAT:
                raise ValueError(f"format {state.get('format')}, not {FORMAT}")
            rows = Rows.load(self.folder)
            vectors = {name: Vectors.load(self.folder, base)
                       for name, base in state["files"].items()}
            if any(len(v.present) > len(rows) for v in vectors.values()):
                raise ValueError("a save did not finish (vectors of rows not written)")
        except FileNotFoundError:
            return
        except (ValueError, KeyError, TypeError, RuntimeError, OSError, BadZipFile) as error:
            log.warning("similarity: the index in %s is not usable (%s): rebuilding it",
                        self.folder, error)
            return
        self.rows, self.vectors = rows, vectors

    # --- searching -------------------------------------------------------------------------

    def descriptors_of(self, cluster_id: ObjectId) -> dict[str, np.ndarray]:
        """The stored vectors of an indexed cluster (empty when it is not indexed)."""
        with self.lock:
            row = self.rows.row_of.get(cluster_id)
            if row is None:
                return {}
            return {name: vectors.matrix[row].copy() for name, vectors in self.vectors.items()
                    if vectors.has(np.array([row]))[0]}

    def holds(self, cluster_id: ObjectId) -> bool:
        """Whether the cluster was in the database when the index last caught up."""
        with self.lock:
            return self.rows.holds(cluster_id)

    def names(self) -> list[str]:
        with self.lock:
            return sorted(self.vectors)

    def search(self, query: Mapping[str, np.ndarray], k: int, where: RowFilter = RowFilter(),
               exclude: Iterable[ObjectId] = ()) -> list[Match]:
        """The k clusters most alike the query's descriptors (those the index has), best
        first, among those the filter lets through."""
        with self.lock:
            # Every row, unfiltered: the graph's rows are those in the database already.
            passing = self.rows.passing(where) if where.narrows() else None
            excluded = {self.rows.row_of[oid] for oid in exclude if oid in self.rows.row_of}
            wanted = {name: np.asarray(v, np.float32) for name, v in query.items()
                      if name in self.vectors and self.vectors[name].ndim == np.size(v)}
            candidates: set[int] = set()
            for name, vector in wanted.items():
                candidates |= self._nearest(self.vectors[name], vector, 2 * k + len(excluded),
                                            passing)
            return self._ranked(wanted, np.array(sorted(candidates - excluded), np.int64), k)

    def _nearest(self, vectors: Vectors, vector: np.ndarray, count: int,
                 passing: Selection | None) -> set[int]:
        """The `count` rows nearest the vector among those passing (None: all): exactly
        among up to EXACT_ROWS, else from ever more neighbours until enough pass."""
        if passing is not None and len(passing) <= EXACT_ROWS:
            return set(vectors.best_of(passing, vector, count).tolist())
        held = len(vectors.index)
        fetch = count * 2 if passing is None else int(count * held / len(passing) * 2)
        if passing is not None:
            allowed = np.zeros(len(self.rows), bool)
            allowed[passing.rows()] = True
        while held:
            keys = vectors.nearest(vector, fetch)
            if passing is not None:
                keys = keys[allowed[keys]]
            if len(keys) >= count or fetch >= held:
                return set(keys[:count].tolist())
            fetch *= 4
        return set()

    def _ranked(self, query: Mapping[str, np.ndarray], rows: np.ndarray, k: int
                ) -> list[Match]:
        if not len(rows):
            return []
        scores = {}
        for name, vector in query.items():
            vectors = self.vectors[name]
            present = vectors.has(rows)
            score = np.full(len(rows), np.nan)
            score[present] = np.clip(vectors.scores(rows[present], vector), 0, 1)
            scores[name] = score
        table = np.array(list(scores.values()))
        combined = np.nanmean(table, axis=0)
        order = np.argsort(-combined, kind="stable")[:k]
        return [Match(self.rows.ids[rows[i]], round(float(combined[i]), 4),
                      {name: round(float(s[i]), 4) for name, s in scores.items()
                       if not np.isnan(s[i])})
                for i in order]


def _kth_largest(values: np.ndarray, k: int) -> float:
    return np.partition(values, len(values) - k)[len(values) - k]


def described_kinds() -> list[str]:
    """The stored names (aliases too) of the hypothesis and annotation types that give
    descriptors: a cluster's other parts (most of its twenty) need not be read to index it."""
    return sorted(name for cls in registered_types().values()
                  if issubclass(cls, Hypothesis | Annotation)
                  and cls.descriptors not in (Hypothesis.descriptors, Annotation.descriptors)
                  for name in (name_of(cls), *aliases_of(cls)))


@functools.cache
def scanners() -> ThreadPoolExecutor:
    """The threads that scan parts of a filter's rows beside the asking one: np.take and
    numkong let go of the GIL, so two cores scan 73,000 rows in 2.0 ms where one takes 3.0
    (fancy indexing holds it: threads were slower with it)."""
    return ThreadPoolExecutor(SCAN_THREADS - 1, thread_name_prefix="similarity-scan")


os.register_at_fork(after_in_child=scanners.cache_clear)  # a fork has none of the threads


@functools.cache
def dots_exact(ndim: int) -> bool:
    """Whether numkong's int8 inner products of this length are exact (checked, not assumed:
    a kernel summing in 16 bits, or in int32 past 133,000 dimensions, would break
    Vectors._rough_scores's bound; then the scan stays float32)."""
    rows = np.random.default_rng(0).integers(-STEPS, STEPS + 1, (64, ndim)).astype(np.int8)
    rows[:2] = [[STEPS], [-STEPS]]  # with rows[0] as the query: the largest sums either way
    return all(np.array_equal(np.asarray(numkong.dots_packed(
        rows, numkong.dots_pack(query[None])))[:, 0], rows.astype(np.int64) @ query)
        for query in (rows[0], rows[2]))


def quantised(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each row (along the last axis) as int8 steps of a scale, its largest |value| / 127, so
    each value is within half a step of scale * steps (a row of zeros: steps 0, scale 0); and
    the row's scale and norm (float64). Divided in float64: no step lands past 127."""
    scales = np.abs(values).max(axis=-1).astype(np.float64) / STEPS
    divided = values / np.where(scales > 0, scales, 1)[..., None]
    norms = np.sqrt(np.einsum("...i,...i->...", values, values, dtype=np.float64))
    return np.rint(divided, out=divided).astype(np.int8), np.stack([scales, norms], axis=-1)


def _file_name(descriptor: str) -> str:
    """A file name for a descriptor's files (names come from types: any characters)."""
    return f"{re.sub(r'[^A-Za-z0-9_.-]', '_', descriptor)}-{zlib.crc32(descriptor.encode())}"
