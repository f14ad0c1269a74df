"""Vector indexes for similarity search ("find more like this"): one approximate-nearest-
neighbour index per descriptor (the named unit vectors types declare: types/appearance.py),
kept in a folder beside the database and derived from it (MongoDB is the source of truth).

Why usearch: of the well-kept ANN libraries on PyPI, usearch ships a 2.3 MB wheel for every
platform, saves and loads (or memory-maps) an index as one file, and removes and adds vectors
in place. hnswlib has no wheel (PyPI holds its source only: a C++ compiler at install time)
and filters through a Python callback per candidate; faiss-cpu is a 19 MB wheel whose HNSW
index cannot remove a vector. Filters need no help from the library: every cluster's time,
robot, region and map never change once stored, so the index keeps them as numpy arrays (a
row per cluster) and a filter selects rows (a time window by the rows sorted by time, the
rest by masks over the window's rows). When at most EXACT_ROWS pass, those
rows are searched exactly, from the vectors kept a second time as a matrix by row (memory
for speed: a graph search has to fetch ~2k / (share passing) neighbours to keep k); else the
graph's neighbours are over-fetched and kept when they pass. The exact search scans an int8
copy of the matrix (a scale per row; derived when loaded, never saved) and scores again in
float32 only the rows its bound on the rounding leaves in doubt: its results are the float32
scan's, at a quarter of the bytes fetched.

Kept current from a watermark, not a pipeline stage: the folder is local to each process
(`pmem serve`, `pmem query`) while MongoDB may be shared, so each process's index catches up
by itself before it answers (`refresh`): it reads the ids of the clusters stored since it last
read them (ids newer than that time less a margin: ids come from the storing clients' clocks,
before their transactions commit) and adds those it lacks. Not since the newest id it holds:
after a burst of ingest, every query would read the burst's last margin of ids again (22,000 at
2,200 clusters/s) until the next cluster is stored. When the count of clusters still differs
(ids older than the margin, clusters removed) it compares every id with MongoDB's and adds or
removes the difference. Storing a scene does
no index work at all; the first query after a burst of ingest pays for it.
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

from .schema import CLUSTERS, SCENES
from .settings import Settings
from .store import MemoryStore

log = logging.getLogger(__name__)

FORMAT = 2  # of the folder's files: another number means rebuild
# How long before a refresh read them a cluster's id may have been made and still not be
# committed (ids come from the clock of the client that stored it, before its transaction
# commits). Later ones are found by the count check; a wider margin costs every refresh the ids
# stored in it.
MARGIN = timedelta(seconds=10)
EXPANSION_SEARCH = 128  # usearch's default 64 finds half the true 10 nearest of random data
CHUNK = 500  # clusters read and described at a time
PROGRESS_EVERY = 100  # chunks: a build from a large database logs how far it is
# When a filter passes at most this many rows they are searched exactly. Exact is always right,
# a filtered graph search is not: the nearest rows passing a narrow filter are often far, where
# the graph finds few of them (a robot and a day, 7 % of a million rows: the true top 10 for 1
# query of 150); so exact as long as it stays cheap: its cost is the rows', ~0.03 us each.
EXACT_ROWS = 100_000
SCORE_BLOCK = 2048  # rows gathered and scored at a time (~1 MB of 144 floats: in the cache)
SCAN_THREADS = os.cpu_count() or 1  # a filter's rows are scanned in this many parts at once
QUANTISE_BLOCK = 65_536  # rows made int8 at a time when loaded (each a float64 row meanwhile)
STEPS = 127  # int8 steps each side of zero: a row's largest |value| is 127 of its scale
FLOAT32_EPS = float(np.finfo(np.float32).eps)  # per term, bounds a float32 sum's own error
FLOAT32_TINY = float(np.finfo(np.float32).smallest_subnormal)  # bounds a product's underflow
FLOAT32_MAX = float(np.finfo(np.float32).max)
# The bound's share for float64's own rounding (of the int8 scores, the bounds, their sums):
# ~2^-52 of |q| |x|, where a row's bound is at least ndim * FLOAT32_EPS (2^-23) of it.
SLACK = 2.0**-20
SAVE_EVERY = 1000  # rows added or removed since the files were written
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
        self._by_time = np.zeros(0, np.int64)  # rows sorted by time (see passing)
        self._sorted = {key: np.zeros(0, COLUMNS[key]) for key in META}  # their columns

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

    def passing(self, f: RowFilter) -> np.ndarray:
        """The rows that pass the filter (and are still in the database), in no set order.
        With a time window only its rows are looked at, a slice of the columns kept sorted by
        time: a day's filter over a million rows costs as that day's rows do, not as all of
        them, without gathering their columns from rows all over (and they stay in time order:
        sorting them by row would cost a tenth of scanning them)."""
        n = len(self)
        if f.after is None and f.before is None:
            live = self.columns["live"][:n]
            return np.flatnonzero(live & self._matching(f, self.columns, slice(0, n)))
        order, columns = self._time_order()
        first = 0 if f.after is None else np.searchsorted(columns["time"], f.after, "left")
        end = n if f.before is None else np.searchsorted(columns["time"], f.before, "right")
        rows = order[first:end]
        if f.robot or f.region or f.map:
            rows = rows[self._matching(f, columns, slice(first, end))]
        return rows[self.columns["live"][rows]]

    def _matching(self, f: RowFilter, columns: Mapping[str, np.ndarray], part: slice
                  ) -> np.ndarray:
        """Which of the columns' rows in `part` have one of the filter's robots, regions and
        maps (all, when it names none)."""
        keep = np.ones(part.stop - part.start, bool)
        for key in META[1:]:
            wanted = getattr(f, key)
            if wanted:
                codes = {self._code_of[key][v] for v in wanted if v in self._code_of[key]}
                matched = np.zeros(len(keep), bool)
                for code in codes:  # a comparison per name: faster than gathering by code
                    matched |= columns[key][part] == code
                keep &= matched
        return keep

    def _time_order(self) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """The rows sorted by time, and their time, robot, region and map in that order (they
        never change once stored): the rows added since the last call are merged in (sorting
        only them), so new clusters cost a copy, not a sort of all."""
        done, n = len(self._by_time), len(self)
        if done < n:
            order = np.argsort(self.columns["time"][done:n], kind="stable")
            at = np.searchsorted(self._sorted["time"], self.columns["time"][done:n][order],
                                 "right")
            self._by_time = np.insert(self._by_time, at, order + done)
            for key, column in self._sorted.items():
                self._sorted[key] = np.insert(column, at, self.columns[key][done:n][order])
        return self._by_time, self._sorted

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


class Vectors:
    """One descriptor's vectors, three times: in an HNSW graph (usearch) for the nearest among
    many rows; as a matrix by row for exact scores of a few (a filter's rows, the candidates):
    gathering and multiplying 36,000 rows of a million takes a few milliseconds, fetching as
    many neighbours from the graph ten times that; and that matrix in int8 (a scale per row),
    for a filter's rows: gathering and multiplying 73,000 rows is the exact search's cost, and
    int8 rows are a quarter of the bytes with integer products. It is derived from the float32
    matrix, not saved."""

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

    @property
    def ndim(self) -> int:
        return self.matrix.shape[1]

    def add(self, rows: np.ndarray, stack: np.ndarray) -> None:
        held = len(self.present)
        if rows.max() >= held:
            size = max(16, 2 * held, int(rows.max()) + 1)
            self.matrix = np.resize(self.matrix, (size, self.ndim))
            self.steps = np.resize(self.steps, (size, self.ndim))
            self.sizes = np.resize(self.sizes, (size, 2))
            self.present = np.resize(self.present, size)
            self.present[held:] = False
        self.matrix[rows] = stack
        self.steps[rows], self.sizes[rows] = quantised(stack)
        self.reach = max(self.reach, float(self.sizes[rows, 1].max()))
        self.present[rows] = True
        self.index.add(rows.astype(np.uint64), stack)

    def remove(self, row: int) -> None:
        if self.has(np.array([row]))[0]:
            self.present[row] = False
            self.index.remove(row)

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
        """The `count` rows (of these, which have this descriptor) that score highest in
        float32, in no order; of rows scoring as the count-th does, the first added. The int8
        copy is scanned; a row whose int8 score could, within its bound, reach the count-th
        best's lowest possible score may be among them, and only those rows are scored again in
        float32: the rows found are the float32 scan's, whatever order the rows come in."""
        rough = self._rough_scores(rows, vector) if len(rows) > count else None
        if rough is not None:
            scores, bounds = rough
            rows = rows[scores + bounds >= _kth_largest(scores - bounds, count)]
        if len(rows) <= count:
            return rows
        scores = self.scores(rows, vector)
        kth = _kth_largest(scores, count)
        above = rows[scores > kth]
        return np.concatenate([above, np.sort(rows[scores == kth])[:count - len(above)]])

    def _rough_scores(self, rows: np.ndarray, vector: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray] | None:
        """The rows' int8 scores with the vector quantised alike, and how far each may be from
        its float32 score; None when that cannot be bounded (numkong's int8 sums not exact
        here, or float32 sums that may overflow: then the scan stays float32).
        With x ~ s x8 (each value within s/2) and q ~ t q8, the int8 score is s t (q8.x8),
        exact in int32, and |q.x - s t q8.x8| <= |q|_1 s/2 + |q - t q8| (|x| + sqrt(ndim)
        s/2); float32's own sum is within ndim eps |q| |x| (+ underflow) of q.x. Rows are
        gathered by np.take: fancy indexing copies rows of int8 a value at a time, 2x slower."""
        query = vector.astype(np.float64)
        length = float(np.linalg.norm(query))
        if not dots_exact(self.ndim) or not length * self.reach < FLOAT32_MAX / 2:
            return None
        steps, (scale, _) = quantised(query)
        packed = numkong.dots_pack(steps[None])
        scores = np.empty(len(rows))

        def scan(part: range) -> None:
            for start in part:
                block = np.take(self.steps, rows[start:start + SCORE_BLOCK], axis=0)
                found = numkong.dots_packed(block, packed)  # int32, (rows, 1)
                scores[start:start + len(block)] = np.asarray(found)[:, 0]

        starts = range(0, len(rows), SCORE_BLOCK)
        share = max(1, min(SCAN_THREADS, len(starts)))  # every share-th block to a thread
        helped = [scanners().submit(scan, starts[i::share]) for i in range(1, share)]
        scan(starts[::share])
        for part in helped:
            part.result()
        sizes = np.take(self.sizes, rows, axis=0)
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
        self.lock = threading.RLock()
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
        with self.lock:
            if not self._loaded:
                self.load()
            changed = self._add(self._recent_unknown())
            clusters = self.store.db[CLUSTERS].estimated_document_count()
            if clusters != self.rows.live_count():
                changed += self._reconcile()
            self.unsaved += changed
            if self.unsaved >= SAVE_EVERY or (self.unsaved and not self._saved_once()):
                self.save()
            return changed

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
            clusters = self.store.get_clusters(chunk)
            meta = {d["_id"]: d for d in self.store.db[CLUSTERS].find(
                {"_id": {"$in": list(chunk)}},
                {"scene_id": 1, "search.time": 1, "search.robot": 1, "search.region": 1})}
            maps = {d["_id"]: d.get("map") for d in self.store.db[SCENES].find(
                {"_id": {"$in": [d.get("scene_id") for d in meta.values()]}}, {"map": 1})}
            self.add(Entry(cluster_id, search.get("time", 0), search.get("robot"),
                           search.get("region"), maps.get(meta[cluster_id].get("scene_id")),
                           cluster.descriptors())
                     for cluster_id, cluster in clusters.items()
                     for search in [meta[cluster_id].get("search", {})])
            if start // CHUNK % PROGRESS_EVERY == PROGRESS_EVERY - 1:
                log.info("similarity: %d of %d clusters indexed", start + len(chunk),
                         len(cluster_ids))
        return len(cluster_ids)

    def add(self, entries: Iterable[Entry]) -> None:
        """Add clusters with their descriptors (non-finite vectors are left out)."""
        with self.lock:
            self._loaded = True
            vectors: dict[str, tuple[list[int], list[np.ndarray]]] = {}
            for entry in entries:
                row = self.rows.add(entry.cluster_id, entry.time, {
                    "robot": entry.robot, "region": entry.region, "map": entry.map})
                for name, vector in entry.descriptors.items():
                    if np.all(np.isfinite(vector)):
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
                 passing: np.ndarray | None) -> set[int]:
        """The `count` rows nearest the vector among those passing (None: all): exactly
        among up to EXACT_ROWS, else from ever more neighbours until enough pass."""
        if passing is not None and len(passing) <= EXACT_ROWS:
            return set(vectors.best(passing[vectors.has(passing)], vector, count).tolist())
        held = len(vectors.index)
        fetch = count * 2 if passing is None else int(count * held / len(passing) * 2)
        if passing is not None:
            allowed = np.zeros(len(self.rows), bool)
            allowed[passing] = True
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
