"""Export benchmark; prints JSON: throughput and peak memory of exports of growing size.

Builds a memory of --clusters clusters (default 100,000) in a scratch database: the kitchen
week's scenes and clusters (64 px crops and masks, classifications, ...) as documents.py lays
them out, copied with new ids and times, inserted prepared and in bulk (as bench/queries.py
does; colour histograms left out to keep the build small). Then each format in --formats is
exported at each size in --sizes (the oldest clusters, `limit`) through Export.zip_stream,
the path GET /api/export takes, into a sink that only counts the bytes.

Each export runs in a fresh process whose peak resident memory is reset (/proc/self/clear_refs)
once it has imported everything and connected (`baseline_rss_mb`), so `peak_rss_mb` is the
export's own (/proc/self/status VmHWM) and `growth_mb` the peak above the baseline. Memory
must not grow with the export size: the peak at 100,000 clusters should be that at 10,000.

Usage: python bench/export.py [--clusters N] [--sizes 10000,100000] [--formats ...]
       [--keep DB]   (uses MONGODB_URI or the embedded mongod)
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time

import bson
from bson import ObjectId
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rss import reset_peak, rss_mb
from scratch import print_json, scratch_store

from percept_memory.demo import kitchen_week as kw
from percept_memory.memory import documents
from percept_memory.memory.schema import CLUSTERS, SCENES
from percept_memory.memory.settings import Settings
from percept_memory.memory.store import MemoryStore
from percept_memory.queries.export.model import ExportQuery
from percept_memory.queries.export.run import Export

HISTOGRAM = "pm.annotation.ColorHistogram"


def templates() -> list[tuple[dict, list[dict]]]:
    """(scene document, its cluster documents) of a kitchen day, without colour histograms."""
    week = kw.generate(days=1)
    for scene in week.scenes:
        scene.ensure_id()
    written = documents.scene_documents(week.scenes, threshold=2**30)
    clusters = {doc["_id"]: doc for doc in (bson.decode(raw.raw) for raw in written.clusters)}
    for doc in clusters.values():
        doc["annotations"] = [a for a in doc["annotations"] if a["_type"] != HISTOGRAM]
    scenes = [bson.decode(raw.raw) for raw in written.scenes]
    return [(scene, [clusters[c] for c in scene["clusters"]]) for scene in scenes
            if scene["clusters"]]


def build(store: MemoryStore, count: int, progress: Progress, batch: int = 2000) -> None:
    """`count` clusters in scenes copied from the templates, one scene every 30 s."""
    kinds = templates()
    task = progress.add_task("build", total=count)
    built, n = 0, 0
    scenes, clusters = [], []
    while built < count:
        scene, members = kinds[n % len(kinds)]
        members = members[:count - built]
        t = kw.timestamp_from_datetime(kw.START) + n * 30 * kw.SECOND
        scene_id = ObjectId()
        copies = [{**doc, "_id": ObjectId(), "scene_id": scene_id,
                   "search": {**doc["search"], "time": t}} for doc in members]
        scenes.append({**scene, "_id": scene_id, "timestamp": t,
                       "clusters": [c["_id"] for c in copies]})
        clusters += copies
        built, n = built + len(copies), n + 1
        if len(clusters) >= batch or built == count:
            store.db[SCENES].insert_many(scenes, ordered=False)
            store.db[CLUSTERS].insert_many(clusters, ordered=False)
            progress.advance(task, len(clusters))
            scenes, clusters = [], []


def measure(db: str, fmt: str, size: int) -> dict:
    """One export in this process: its throughput and peak memory."""
    settings = Settings(db=db)
    with MemoryStore.open(settings) as store:
        baseline = rss_mb("VmRSS")
        reset_peak()
        start = time.perf_counter()
        export = Export(store, ExportQuery(format=fmt, limit=size,
                                           **({"images": "crops"} if fmt == "coco" else {})))
        size_bytes = chunks = 0
        for chunk in export.zip_stream():
            size_bytes += len(chunk)
            chunks += 1
        seconds = time.perf_counter() - start
    peak = rss_mb("VmHWM")
    return {"format": fmt, "clusters": export.summary.exported,
            "skipped": sum(export.summary.skipped.values()), "seconds": round(seconds, 1),
            "clusters_per_s": round(export.summary.exported / seconds),
            "zip_mb": round(size_bytes / 2**20, 1), "chunks": chunks,
            "baseline_rss_mb": round(baseline), "peak_rss_mb": round(peak),
            "growth_mb": round(peak - baseline)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--clusters", type=int, default=100_000)
    parser.add_argument("--sizes", default="10000,100000")
    parser.add_argument("--formats", default="imagefolder,coco")
    parser.add_argument("--keep", metavar="DB", help="build into DB (once) and keep it")
    parser.add_argument("--measure", nargs=3, metavar=("DB", "FORMAT", "SIZE"),
                        help=argparse.SUPPRESS)  # one export, in a child process
    args = parser.parse_args()
    if args.measure:
        db, fmt, size = args.measure
        json.dump(measure(db, fmt, int(size)), sys.stdout)
        return
    with scratch_store(args.keep) as store, Progress(
            TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
            TimeElapsedColumn(), console=Console(stderr=True), transient=True) as progress:
        start = time.perf_counter()
        reuse = args.keep and store.clusters.estimated_document_count() == args.clusters
        if not reuse:
            store.clusters.delete_many({})
            store.scenes.delete_many({})
            build(store, args.clusters, progress)
        built = time.perf_counter() - start
        runs = []
        plan = [(f, int(s)) for f in args.formats.split(",") for s in args.sizes.split(",")]
        task = progress.add_task("exports", total=len(plan))
        for fmt, size in plan:
            child = subprocess.run(
                [sys.executable, __file__, "--measure", store.db.name, fmt, str(size)],
                check=True, capture_output=True, text=True)
            runs.append(json.loads(child.stdout))
            progress.advance(task)
    print_json({"benchmark": "export", "clusters_in_store": args.clusters,
                "build_s": None if reuse else round(built, 1), "exports": runs})


if __name__ == "__main__":
    main()
