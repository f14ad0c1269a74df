"""Similarity search benchmark ("find more like this"); prints JSON.

1. Precision@10 of "same item" on the kitchen week: from every cluster of the week (or every
   n-th), `Similarity.similar_to(cluster, k=10, descriptor=[...])` as the API asks it, and the
   share of the ten found that show the same catalogue item (the three identical cups count
   as one item), per descriptor and combined (every descriptor). Also the index's build from
   MongoDB (reading and describing every cluster, crops decoded).
2. Latency at scale: an index of N synthetic rows (random unit vectors of the largest crop
   descriptor's size, 144; four regions, two robots, a week of times) built straight into
   the index (not through MongoDB: storing a million clusters is another benchmark's job),
   its build time and size on disk; p50/p95 of a filtered search (one region and one day:
   about 1/28 of the rows) and of an unfiltered one, and recall@10 against exact search.
   Random vectors are the hard case for a graph index; real descriptors cluster.
3. Ingest: storing scenes does no index work (the index catches up from MongoDB when it is
   next asked, memory/similarity.py), so ingest is not slowed at all; what it costs instead
   is the catch-up, measured here as the refresh after storing synthetic scenes in process,
   and as the slowdown ingest would see if that work were done inline.

Usage: python bench/similarity.py [--days N] [--every N] [--vectors N] [--scenes N]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from collections import Counter
from pathlib import Path

import numpy as np
from bson import ObjectId
from ingest import kitchen_image, scenes
from scratch import print_json, scratch_store

from percept_memory.demo import kitchen_week
from percept_memory.ingest.service import IngestService
from percept_memory.memory.settings import collect_less
from percept_memory.memory.similarity import Entry, RowFilter, SimilarityIndex
from percept_memory.queries.ops import QueryError
from percept_memory.queries.similar import Similarity

DAY = 86_400 * 10**9
CHUNK = 50_000  # rows added to the index at a time
REGIONS = ["counter_top_sink", "counter_top_island", "table", "shelf"]
LATENCY_TARGET_MS = 10.0
SLOWDOWN_TARGET = 0.10


def precision(days: int, every: int, folder: Path) -> dict:
    week = kitchen_week.generate(days=days)
    with scratch_store() as store:
        results = store.put_scenes(week.scenes)
        item = {cluster_id: kitchen_week.item_of(week.truth.object_at(i, j)).key
                for i, stored in enumerate(results) for j, cluster_id in
                enumerate(stored.cluster_ids)}
        index = SimilarityIndex(store, folder / "week")
        start = time.perf_counter()
        index.refresh()
        build_s = time.perf_counter() - start
        search = Similarity(store, index=index)
        starts = list(item)[::every]
        per = {}
        for name in [*index.names(), "combined"]:
            chosen = [] if name == "combined" else [name]
            scores, took = [], []
            for cluster_id in starts:
                begin = time.perf_counter()
                try:
                    found = search.similar_to(cluster=cluster_id, k=10, descriptor=chosen).items
                except QueryError:
                    continue  # this cluster has no such descriptor
                took.append(time.perf_counter() - begin)
                scores.append(np.mean([item[h.id] == item[cluster_id] for h in found]))
            per[name] = {"precision_at_10": round(float(np.mean(scores)), 3),
                         "queries": len(scores),
                         "p95_ms_similar_to": round(float(np.percentile(took, 95)) * 1e3, 2)}
    return {"days": days, "clusters": len(item), "items": len(set(item.values())),
            "observations_per_item": dict(Counter(item.values()).most_common()),
            "index_build_from_mongodb_s": round(build_s, 2),
            "index_build_clusters_per_s": round(len(item) / build_s),
            "per_descriptor": per}


def at_scale(count: int, folder: Path, queries: int = 200) -> dict:
    rng = np.random.default_rng(0)
    index = SimilarityIndex(None, folder / "scale")  # type: ignore[arg-type]  # no MongoDB
    times = rng.integers(0, 7 * DAY, count)
    regions = rng.integers(0, len(REGIONS), count)
    robots = rng.integers(0, 2, count)
    vectors = rng.normal(size=(count, 144)).astype(np.float32)
    vectors /= np.linalg.norm(vectors, axis=1, keepdims=True)
    start = time.perf_counter()
    for chunk in range(0, count, CHUNK):
        index.add(Entry(ObjectId(), int(times[i]), f"robot{robots[i]}", REGIONS[regions[i]],
                        "bench", {"crop-hog": vectors[i]})
                  for i in range(chunk, min(chunk + CHUNK, count)))
    add_s = time.perf_counter() - start
    start = time.perf_counter()
    index.save()
    save_s = time.perf_counter() - start
    size = sum(f.stat().st_size for f in (folder / "scale").iterdir())
    start = time.perf_counter()
    loaded = SimilarityIndex(None, folder / "scale")  # type: ignore[arg-type]
    loaded.load()
    load_s = time.perf_counter() - start

    probes = rng.normal(size=(queries, 144)).astype(np.float32)
    probes /= np.linalg.norm(probes, axis=1, keepdims=True)
    filtered = RowFilter(region=["table"], after=2 * DAY, before=3 * DAY - 1)
    latency = {}
    for name, where in (("filtered_region_and_day", filtered), ("unfiltered", RowFilter())):
        took = []
        for probe in probes:
            begin = time.perf_counter()
            loaded.search({"crop-hog": probe}, 10, where)
            took.append(time.perf_counter() - begin)
        latency[name] = {"p50_ms": round(float(np.percentile(took, 50)) * 1e3, 2),
                         "p95_ms": round(float(np.percentile(took, 95)) * 1e3, 2)}
    latency["filtered_region_and_day"]["share_of_rows"] = round(
        float(loaded.rows.mask(filtered).mean()), 4)
    recall = []
    for probe in probes[:20]:
        exact = set(np.argsort(-(vectors @ probe))[:10].tolist())
        found = loaded.search({"crop-hog": probe}, 10)
        recall.append(len(exact & {loaded.rows.row_of[m.cluster_id] for m in found}) / 10)
    p95 = latency["filtered_region_and_day"]["p95_ms"]
    return {"vectors": count, "dimensions": 144,
            "build_s": round(add_s + save_s, 1),
            "build_parts_s": {"add": round(add_s, 1), "save": round(save_s, 1)},
            "load_s": round(load_s, 1), "size_mb": round(size / 2**20, 1),
            "size_mb_per_million": round(size / 2**20 * 1e6 / count, 1),
            "latency": latency, "recall_at_10_unfiltered": round(float(np.mean(recall)), 3),
            "target_p95_ms": LATENCY_TARGET_MS, "met": p95 < LATENCY_TARGET_MS}


def ingest_cost(count: int, folder: Path) -> dict:
    image = kitchen_image()
    with scratch_store() as store:
        index = SimilarityIndex(store, folder / "ingest")
        index.refresh()
        generated = scenes(count, 1_700_000_000_000_000_000, image, seed=1)
        service = IngestService(store, batch_size=32)
        start = time.perf_counter()
        for _ in service.ingest_stream((str(i), s) for i, s in enumerate(generated)):
            pass
        ingest_s = time.perf_counter() - start
        start = time.perf_counter()
        added = index.refresh()
        refresh_s = time.perf_counter() - start
        start = time.perf_counter()
        index.refresh()
        idle_s = time.perf_counter() - start
    slowdown = refresh_s / ingest_s
    return {"scenes": count, "clusters": added,
            "ingest_clusters_per_s_no_index_work": round(added / ingest_s),
            "ingest_slowdown": 0.0,
            "catch_up_s": round(refresh_s, 2),
            "catch_up_clusters_per_s": round(added / refresh_s),
            "slowdown_if_inline": round(slowdown, 3),
            "target_slowdown": SLOWDOWN_TARGET, "met_if_inline": slowdown <= SLOWDOWN_TARGET,
            "refresh_with_nothing_new_ms": round(idle_s * 1e3, 1)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--days", type=int, default=7)
    parser.add_argument("--every", type=int, default=3, help="query from every n-th cluster")
    parser.add_argument("--vectors", type=int, default=1_000_000)
    parser.add_argument("--scenes", type=int, default=300)
    args = parser.parse_args()
    collect_less()
    with tempfile.TemporaryDirectory() as folder:
        print_json({
            "benchmark": "similarity",
            "kitchen_week": precision(args.days, args.every, Path(folder)),
            "at_scale": at_scale(args.vectors, Path(folder)),
            "ingest": ingest_cost(args.scenes, Path(folder)),
        })


if __name__ == "__main__":
    main()
