"""Side by side with FiftyOne on the same percepts; prints JSON.

The same generated percepts (bench/percepts.py: --count of one shape, each a 64 px crop, a
detection, a classification, x, y, z, region, time and text) go into each system, each on a
mongod of its own (the same binary, the one percept-memory runs; a 1 GB WiredTiger cache
each; ours a single-node replica set as always, FiftyOne's standalone as its own launcher
makes it), both with their best indexes before the percepts go in. Then:
- ingest: percepts per second through each one's Python API (ours: IngestService, one scene
  per percept, its crop as pixels; FiftyOne: add_samples, its crop a PNG file written before
  the clock starts, as FiftyOne keeps media on disk), generating the percepts included;
- queries, interleaved (the same random arguments to both, one after the other), each as a
  count and as the first 50 materialised newest first: label, text word, one hour, 3D box,
  sphere, region + one day, the 50 nearest. FiftyOne's label is classification.label; ours
  is asked twice: `label` (`labelled=`, any annotator's) and `label_field` (a predicate on
  the classification's class_name, with the field index `pmem index add` makes). `ratio` is
  FiftyOne's p50 / ours (> 1: we are faster); `same_n` compares what the two found;
- footprint: data and index bytes per percept in each database (FiftyOne's media files apart);
- COCO export of the oldest --export percepts, each in a fresh process: time, peak memory.
FiftyOne runs in its own Python (bench/fiftyone_side.py, talked to by JSON lines), which
must have `fiftyone` installed: this script installs nothing. Without it, FiftyOne's side is
skipped with a message and ours is measured alone. Both mongods and their files are removed
at the end.

Usage: python bench/vs_fiftyone.py [--count 100000] [--reps 50] [--export 10000]
       [--fiftyone-python PATH]   (default: this Python; e.g. a venv with fiftyone==1.22.1)
       [--gridfs-threshold BYTES] (ours: binaries larger leave the cluster documents)
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from contextlib import ExitStack, contextmanager
from pathlib import Path

import numpy as np
from percepts import percepts, query_args
from pymongo import MongoClient
from scratch import footprint, print_json

from percept_memory.ingest.service import IngestService
from percept_memory.memory.mongod import EmbeddedMongod, find_mongod
from percept_memory.memory.settings import Settings
from percept_memory.memory.store import MemoryStore
from percept_memory.memory.types import (
    Classification,
    Cluster,
    Detection,
    Image,
    ImageROI,
    Location,
    Scene,
    Text,
)
from percept_memory.queries.engine import QueryEngine

HERE = Path(__file__).resolve().parent
CACHE_GB = 1.0
PAGE = 50
MODES = ("count", "page")
LABEL_FIELD = "class_name"  # ours: the field index a label query wants (pmem index add)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextmanager
def our_mongod(root: Path):
    server = EmbeddedMongod(root / "ours", free_port(), CACHE_GB, oplog_mb=256)
    try:
        yield server.start()
    finally:
        server.stop()


@contextmanager
def standalone_mongod(root: Path):
    """A plain mongod, as FiftyOne's own launcher starts one."""
    port, path = free_port(), root / "fiftyone"
    path.mkdir()
    process = subprocess.Popen(
        [str(find_mongod()), "--dbpath", str(path), "--port", str(port), "--bind_ip",
         "127.0.0.1", "--wiredTigerCacheSizeGB", str(CACHE_GB), "--logpath",
         str(path / "mongod.log")], stdout=subprocess.DEVNULL)
    uri = f"mongodb://127.0.0.1:{port}/?directConnection=true"
    try:
        with MongoClient(uri, serverSelectionTimeoutMS=30_000) as client:
            client.admin.command("ping")
        yield uri
    finally:
        process.terminate()
        process.wait(60)


def scene(p: dict) -> Scene:
    """A percept as percept-memory takes it: a scene with one cluster."""
    x, y, w, h = p["box"]
    box = (int(x * 640), int(y * 480), int(w * 640), int(h * 480))
    return Scene(timestamp=p["time"], robot="pr2", clusters=[Cluster(
        hypotheses=[ImageROI(box=box, crop=Image(data=p["crop"], encoding="bgr8"))],
        annotations=[
            Location(source="RegionFilter", region=p["region"], position=(p["x"], p["y"], p["z"])),
            Classification(source="classifier", class_name=p["label"],
                           confidence=p["confidence"]),
            Detection(source="detector", name=p["label"], confidence=p["confidence"], box=box),
            Text(source="ocr", text=p["text"])])])


class Ours:
    def __init__(self, uri: str, gridfs_threshold: int):
        self.store = MemoryStore.open(Settings(mongodb_uri=uri, db="pmem_vs_fo",
                                               gridfs_threshold=gridfs_threshold))
        self.store.add_field_index(LABEL_FIELD)
        self.engine = QueryEngine(self.store)

    def ingest(self, count: int, seed: int) -> dict:
        service = IngestService(self.store)
        start = time.perf_counter()
        for _ in service.ingest_stream((str(i), scene(p))
                                       for i, p in enumerate(percepts(count, seed))):
            pass
        return {"seconds": time.perf_counter() - start,
                "samples": self.store.clusters.estimated_document_count()}

    def query(self, kind: str, mode: str, args: dict) -> dict:
        start = time.perf_counter()
        if kind == "knn":
            found = len(self.engine.clusters(near=args["near"], k=args["k"]).items)
        else:
            page = self.engine.clusters(**self.filter(kind, args), sort="newest",
                                        **({"limit": 0, "count": True} if mode == "count"
                                           else {"limit": PAGE}))
            found = page.total if mode == "count" else len(page.items)
        return {"ms": (time.perf_counter() - start) * 1000, "n": found}

    @staticmethod
    def filter(kind: str, args: dict) -> dict:
        if kind == "label":
            return {"labelled": [args["label"]]}
        if kind == "label_field":
            return {"where": [f"classification:{LABEL_FIELD}={args['label']}"]}
        if kind == "text":
            return {"text": args["word"]}
        if kind == "hour":
            return args
        if kind == "box":
            return {"box": {"low": args["low"], "high": args["high"]}}
        if kind == "sphere":
            return {"sphere": args}
        if kind == "region_time":
            return {"region": [args["region"]], "after": args["after"],
                    "before": args["before"]}
        raise ValueError(kind)

    def plans(self, kind: str, args: dict) -> list[str]:
        explained: list = []
        engine = QueryEngine(self.store, explain=explained)
        if kind == "knn":
            engine.clusters(near=args["near"], k=args["k"])
        else:
            engine.clusters(**self.filter(kind, args), limit=0, count=True)
        return sorted({s for p in explained for s in p["stages"]})

    def footprint(self) -> dict:
        return footprint(self.store)


class Theirs:
    """FiftyOne's side in its own Python process (bench/fiftyone_side.py)."""

    def __init__(self, python: str, uri: str):
        env = {**os.environ, "FIFTYONE_DATABASE_URI": uri, "FIFTYONE_DO_NOT_TRACK": "true",
               "FIFTYONE_DATABASE_NAME": "fiftyone_vs_pmem", "PYTHONPATH": str(HERE)}
        self.env = env
        self.python = python
        self.process = subprocess.Popen([python, str(HERE / "fiftyone_side.py")], env=env,
                                        stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                        stderr=subprocess.DEVNULL, text=True)

    def __getattr__(self, op: str):
        def call(**args):
            self.process.stdin.write(json.dumps({"op": op, **args}) + "\n")
            self.process.stdin.flush()
            line = self.process.stdout.readline()
            if not line:
                raise RuntimeError(f"FiftyOne's side ended during {op}")
            return json.loads(line)
        return call

    def export(self, directory: str, limit: int) -> dict:
        child = subprocess.run([self.python, str(HERE / "fiftyone_side.py"), "--export",
                                "pmem_vs_fo", directory, str(limit)], env=self.env,
                               check=True, capture_output=True, text=True)
        return json.loads(child.stdout.strip().splitlines()[-1])

    def close(self) -> None:
        self.process.stdin.close()
        self.process.wait(60)


def fiftyone_missing(python: str) -> str | None:
    """Why FiftyOne cannot be measured with this Python, or None when it can."""
    found = subprocess.run([python, "-c", "import fiftyone.core.dataset"],
                           capture_output=True, text=True,
                           env={**os.environ, "FIFTYONE_DO_NOT_TRACK": "true"})
    if found.returncode == 0:
        return None
    return (f"FiftyOne's side skipped: `import fiftyone` fails in {python} "
            f"({found.stderr.strip().splitlines()[-1] if found.stderr.strip() else 'no error text'}"
            "); give --fiftyone-python of an environment with fiftyone installed")


def our_export(uri: str, limit: int) -> dict:
    child = subprocess.run([sys.executable, str(HERE / "export.py"), "--measure", "pmem_vs_fo",
                            "coco", str(limit)], env={**os.environ, "MONGODB_URI": uri},
                           check=True, capture_output=True, text=True)
    return json.loads(child.stdout)


def p50(times: list[float]) -> float:
    return round(statistics.median(times), 2)


def interleaved(sides: dict, count: int, reps: int) -> dict:
    """Every query kind and mode on every side, one after the other, `reps` times (after 5
    rounds of warm-up), the same arguments to all."""
    rng = np.random.default_rng(11)
    times: dict = {}
    found: dict = {}
    for rep in range(reps + 5):
        for kind, args in query_args(rng, count).items():
            for mode in (("page",) if kind == "knn" else MODES):
                for name, side in sides.items():
                    answer = side.query(kind=kind, mode=mode, args=args)
                    if rep >= 5:
                        times.setdefault((kind, mode), {}).setdefault(name, []).append(
                            answer["ms"])
                        found.setdefault((kind, mode), {}).setdefault(name, []).append(
                            answer["n"])
    table = {}
    for (kind, mode), by_side in times.items():
        row = {f"{name}_p50_ms": p50(t) for name, t in by_side.items()}
        row.update({f"{name}_p95_ms": round(float(np.percentile(t, 95)), 2)
                    for name, t in by_side.items()})
        row["mean_n"] = {name: round(statistics.mean(n), 1)
                         for name, n in found[(kind, mode)].items()}
        if "fiftyone" in by_side:
            row["ratio"] = round(row["fiftyone_p50_ms"] / row["ours_p50_ms"], 2)
            row["same_n"] = found[(kind, mode)]["ours"] == found[(kind, mode)]["fiftyone"]
        table[f"{kind}_{mode}"] = row
    return table


def per_percept(stats: dict, count: int) -> dict:
    return {"data_bytes_per_percept": round(stats["data_bytes"] / count),
            "index_bytes_per_percept": round(stats["index_bytes"] / count),
            "mongod_resident_mb": stats["mongod_resident_mb"],
            "mongod_cache_mb": stats["mongod_cache_mb"]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--count", type=int, default=100_000)
    parser.add_argument("--reps", type=int, default=50)
    parser.add_argument("--export", type=int, default=10_000)
    parser.add_argument("--fiftyone-python", default=sys.executable)
    parser.add_argument("--gridfs-threshold", type=int, default=Settings().gridfs_threshold,
                        help="ours: binaries above this many bytes leave the cluster "
                             "documents (the default, 2048: every crop)")
    args = parser.parse_args()
    skipped = fiftyone_missing(args.fiftyone_python)
    if skipped:
        print(skipped, file=sys.stderr)
    result: dict = {"benchmark": "vs_fiftyone", "percepts": args.count, "reps": args.reps,
                    "gridfs_threshold": args.gridfs_threshold,
                    "load_before": os.getloadavg(), "fiftyone": skipped or "measured"}
    with ExitStack() as stack:
        root = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="pmem_vs_fo_")))
        ours = Ours(stack.enter_context(our_mongod(root)), args.gridfs_threshold)
        stack.callback(ours.store.close)
        sides: dict = {"ours": ours}
        if not skipped:
            fo_uri = stack.enter_context(standalone_mongod(root))
            theirs = Theirs(args.fiftyone_python, fo_uri)
            stack.callback(theirs.close)
            sides["fiftyone"] = theirs
        ingest = {"ours": ours.ingest(args.count, seed=7)}
        if not skipped:
            ingest["fiftyone"] = theirs.ingest(count=args.count, seed=7,
                                               media=str(root / "media"))
        for run in ingest.values():
            run["percepts_per_s"] = round(args.count / run["seconds"])
        if not skipped:
            ingest["ratio_ours_to_fiftyone"] = round(
                ingest["ours"]["percepts_per_s"] / ingest["fiftyone"]["percepts_per_s"], 2)
        result["ingest"] = ingest
        result["queries"] = interleaved(sides, args.count, args.reps)
        sample = query_args(np.random.default_rng(3), args.count)
        result["plans"] = {name: {kind: side.plans(kind, a) if name == "ours"
                                  else side.explain(kind=kind, args=a)
                                  for kind, a in sample.items()
                                  if name == "ours" or kind != "knn"}
                           for name, side in sides.items()}
        mine = ours.footprint()
        result["footprint"] = {"ours": mine}
        if not skipped:
            result["footprint"]["fiftyone"] = {
                **per_percept(theirs.footprint(), args.count),
                "media_bytes_per_percept": round(ingest["fiftyone"]["media_bytes"] / args.count)}
        uri = ours.store.client.address
        result["export_coco"] = {"ours": our_export(f"mongodb://{uri[0]}:{uri[1]}/"
                                                    "?directConnection=true", args.export)}
        if not skipped:
            result["export_coco"]["fiftyone"] = theirs.export(str(root / "coco"), args.export)
        result["load_after"] = os.getloadavg()
    print_json(result)


if __name__ == "__main__":
    main()
