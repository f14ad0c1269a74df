"""Converter and store benchmark; prints JSON.

(a) encode + decode throughput of realistic clusters (20 annotations, one a 308-float VFH
    vector, a 64x64 crop from the real kitchen frame) through our codec and BSON, against
    `bson.encode` / `bson.decode` of the equivalent plain dicts. Target: >= 20,000
    annotations/s each way.
(b) storing scenes of 6 such clusters through MemoryStore (ids, encoding, one transaction)
    against raw `insert_one` + `insert_many` of the same, already encoded documents into
    collections with the same indexes, on the same mongod, alternating scene by scene.
    Target: median store time <= 1.5x raw.

Usage: python bench/converter.py [--clusters N] [--scenes N]   (uses MONGODB_URI or the
embedded mongod, in a scratch database that is dropped afterwards)
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import bson
import cv2
import numpy as np
from rich.console import Console
from rich.progress import Progress
from scratch import print_json, scratch_store

from percept_memory.converters import DecodeContext, EncodeContext, decode, encode
from percept_memory.ingest import synthetic
from percept_memory.memory import documents
from percept_memory.memory.schema import CLUSTERS, INDEXES, SCENES
from percept_memory.memory.store import MemoryStore

KITCHEN = Path(__file__).resolve().parents[2] / "shared/data/robosherlock/samples/kitchen"
ANNOTATIONS_PER_CLUSTER = 20


def kitchen_image() -> np.ndarray | None:
    found = sorted(KITCHEN.glob("rgb_*.png"))
    return cv2.imread(str(found[0])) if found else None


def timed(work, items) -> float:
    start = time.perf_counter()
    for item in items:
        work(item)
    return time.perf_counter() - start


def converter_throughput(count: int, image, progress: Progress) -> dict:
    rng = np.random.default_rng(0)
    task = progress.add_task("clusters", total=count)
    clusters = []
    for _ in range(count):
        clusters.append(synthetic.cluster(rng, image))
        progress.advance(task)
    plain = [encode(c) for c in clusters]  # the equivalent plain dicts
    raw = [bson.encode(d) for d in plain]
    annotations = count * ANNOTATIONS_PER_CLUSTER
    ours_encode = timed(lambda c: bson.encode(encode(c, EncodeContext())), clusters)
    ours_decode = timed(lambda r: decode(bson.decode(r), DecodeContext()), raw)
    bson_encode = timed(bson.encode, plain)
    bson_decode = timed(bson.decode, raw)
    return {
        "clusters": count,
        "annotations_per_cluster": ANNOTATIONS_PER_CLUSTER,
        "bytes_per_cluster": round(statistics.mean(len(r) for r in raw)),
        "encode_annotations_per_s": round(annotations / ours_encode),
        "decode_annotations_per_s": round(annotations / ours_decode),
        "bson_encode_annotations_per_s": round(annotations / bson_encode),
        "bson_decode_annotations_per_s": round(annotations / bson_decode),
        "target_annotations_per_s": 20_000,
        "met": min(annotations / ours_encode, annotations / ours_decode) >= 20_000,
    }


def store_overhead(count: int, image, progress: Progress) -> dict:
    with scratch_store() as store:
        return _store_overhead(store, count, image, progress)


def _store_overhead(store: MemoryStore, count: int, image, progress: Progress) -> dict:
    raw_scenes, raw_clusters = store.db["raw_" + SCENES], store.db["raw_" + CLUSTERS]
    raw_scenes.create_indexes(INDEXES[SCENES])
    raw_clusters.create_indexes(INDEXES[CLUSTERS])
    rng = np.random.default_rng(1)
    stamps = iter(range(1_700_000_000_000_000_000, 2**62, 40_000_000))

    def raw_insert(docs: documents.Documents) -> None:
        raw_scenes.insert_many(docs.scenes)
        raw_clusters.insert_many(docs.clusters)

    def as_dicts(written: documents.Documents) -> documents.Documents:
        """The documents as a pymongo user holds them: dicts, encoded by insert_many."""
        return documents.Documents(scenes=[bson.decode(d.raw) for d in written.scenes],
                                   clusters=[bson.decode(d.raw) for d in written.clusters])

    ours, raw = [], []
    task = progress.add_task("scenes", total=count)
    store.put_scene(synthetic.scene(rng, next(stamps), 6, image))  # warm up the catalogue
    for _ in range(count):  # alternate, so both meet the same journal flushes and GC
        scene = synthetic.scene(rng, next(stamps), 6, image)
        ours.append(timed(store.put_scene, [scene]))
        other = synthetic.scene(rng, next(stamps), 6, image)
        documents.assign_ids(other)
        written = as_dicts(documents.scene_documents([other], store.gridfs_threshold))
        raw.append(timed(raw_insert, [written]))
        progress.advance(task)
    ratio = statistics.median(ours) / statistics.median(raw)
    return {
        "scenes": count,
        "clusters_per_scene": 6,
        "store_median_ms": round(1000 * statistics.median(ours), 3),
        "raw_median_ms": round(1000 * statistics.median(raw), 3),
        "store_mean_ms": round(1000 * statistics.mean(ours), 3),
        "raw_mean_ms": round(1000 * statistics.mean(raw), 3),
        "store_scenes_per_s": round(count / sum(ours), 1),
        "raw_insert_scenes_per_s": round(count / sum(raw), 1),
        "overhead_ratio_median": round(ratio, 3),
        "overhead_ratio_mean": round(sum(ours) / sum(raw), 3),
        "target_ratio": 1.5,
        "met": ratio <= 1.5,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--clusters", type=int, default=2000)
    parser.add_argument("--scenes", type=int, default=300)
    args = parser.parse_args()
    image = kitchen_image()
    with Progress(transient=True, console=Console(stderr=True)) as progress:
        result = {
            "benchmark": "converter",
            "crops_from": "real kitchen frame" if image is not None else "random pixels",
            "codec": converter_throughput(args.clusters, image, progress),
            "store": store_overhead(args.scenes, image, progress),
        }
    print_json(result)


if __name__ == "__main__":
    main()
