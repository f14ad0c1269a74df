"""FiftyOne's side of bench/vs_fiftyone.py: run by the Python that has `fiftyone` installed
(its own environment: FiftyOne pins its own pymongo and web stack), on its own mongod
(FIFTYONE_DATABASE_URI), taking one JSON command a line on stdin and answering one JSON line.

Each percept of bench/percepts.py is one sample: its crop a PNG file (FiftyOne keeps media on
disk, by path), a `classification`, a `detections` of one detection, x, y, z, region, time
(int nanoseconds, as ours) and text. Its best indexes: what each query filters and sorts on,
compound where a query has two conditions, and MongoDB's text index for words. Queries go
through FiftyOne's Mongo view stage with plain filters, so that every condition can use its
index (a ViewExpression's $expr cannot use one for every operator).

Usage (by vs_fiftyone.py): FIFTYONE_DATABASE_URI=... python bench/fiftyone_side.py
       python bench/fiftyone_side.py --export DATASET DIR LIMIT   (one export, its own process)
"""

from __future__ import annotations

import json
import os
import sys
import time

from percepts import percepts, png
from rss import reset_peak, rss_mb

PAGE = 50
BUILDING = 100.0  # metres: a cube this half-wide holds the whole building of percepts.py
INDEXES = [[("classification.label", 1), ("time", -1)], [("time", -1)],
           [("region", 1), ("time", -1)], [("x", 1), ("y", 1), ("z", 1)], [("text", "text")]]


def squared_distance(point) -> dict:
    return {"$add": [{"$multiply": [{"$subtract": [f"${a}", point[i]]}] * 2}
                     for i, a in enumerate("xyz")]}


def box(low, high) -> dict:
    return {a: {"$gte": low[i], "$lte": high[i]} for i, a in enumerate("xyz")}


def match(kind: str, args: dict) -> dict:
    if kind in ("label", "label_field"):
        return {"classification.label": args["label"]}
    if kind == "text":
        return {"$text": {"$search": args["word"]}}
    if kind == "hour":
        return {"time": {"$gte": args["after"], "$lte": args["before"]}}
    if kind == "box":
        return box(args["low"], args["high"])
    if kind == "sphere":
        c, r = args["center"], args["radius"]
        return {**box([v - r for v in c], [v + r for v in c]),
                "$expr": {"$lte": [squared_distance(c), r * r]}}
    if kind == "region_time":
        return {"region": args["region"], "time": {"$gte": args["after"], "$lte": args["before"]}}
    raise ValueError(kind)


class Side:
    def __init__(self, name: str):
        import fiftyone as fo

        self.fo = fo
        self.name = name
        self.dataset = None

    def ingest(self, count: int, seed: int, media: str) -> dict:
        fo = self.fo
        os.makedirs(media, exist_ok=True)
        start = time.perf_counter()
        for i, p in enumerate(percepts(count, seed)):
            with open(f"{media}/{i}.png", "wb") as file:
                file.write(png(p["crop"]))
        files_s = time.perf_counter() - start
        media_bytes = sum(e.stat().st_size for e in os.scandir(media))
        if fo.dataset_exists(self.name):
            fo.delete_dataset(self.name)
        self.dataset = fo.Dataset(self.name)
        # the fields declared first, so that their indexes exist while the samples go in
        for field, kind in (("x", fo.FloatField), ("y", fo.FloatField), ("z", fo.FloatField),
                            ("region", fo.StringField), ("time", fo.IntField),
                            ("text", fo.StringField)):
            self.dataset.add_sample_field(field, kind)
        self.dataset.add_sample_field("classification", fo.EmbeddedDocumentField,
                                      embedded_doc_type=fo.Classification)
        self.dataset.add_sample_field("detections", fo.EmbeddedDocumentField,
                                      embedded_doc_type=fo.Detections)
        for spec in INDEXES:
            self.dataset.create_index(spec)

        def samples():
            for i, p in enumerate(percepts(count, seed)):
                yield fo.Sample(
                    filepath=f"{media}/{i}.png",
                    classification=fo.Classification(label=p["label"],
                                                     confidence=p["confidence"]),
                    detections=fo.Detections(detections=[fo.Detection(
                        label=p["label"], bounding_box=p["box"], confidence=p["confidence"])]),
                    x=p["x"], y=p["y"], z=p["z"], region=p["region"], time=p["time"],
                    text=p["text"])

        start = time.perf_counter()
        self.dataset.add_samples(samples(), progress=False)
        seconds = time.perf_counter() - start
        return {"seconds": seconds, "files_s": files_s, "media_bytes": media_bytes,
                "samples": len(self.dataset)}

    def open(self) -> None:
        if self.dataset is None:
            self.dataset = self.fo.load_dataset(self.name)

    def query(self, kind: str, mode: str, args: dict) -> dict:
        self.open()
        start = time.perf_counter()
        if kind == "knn":
            found = self.nearest(args["near"], args["k"])
        else:
            view = self.dataset.mongo([{"$match": match(kind, args)}])
            if mode == "count":
                found = view.count()
            else:
                found = len(list(view.mongo([{"$sort": {"time": -1, "_id": -1}},
                                             {"$limit": PAGE}])))
        return {"ms": (time.perf_counter() - start) * 1000, "n": found}

    def nearest(self, point, k: int) -> int:
        """The k nearest, as a FiftyOne user would find them without a 3D index: the samples
        in a cube around the point (index on x, y, z) ranked by distance, the cube doubled
        until its k-th nearest lies within the radius the cube covers."""
        half = 0.25
        while True:
            view = self.dataset.mongo([
                {"$match": box([v - half for v in point], [v + half for v in point])},
                {"$addFields": {"_d2": squared_distance(point)}},
                {"$sort": {"_d2": 1}}, {"$limit": k}, {"$unset": "_d2"}])
            found = list(view)
            if half >= BUILDING:  # the cube holds every sample
                return len(found)
            if len(found) == k and max(
                    sum((s[a] - point[i]) ** 2 for i, a in enumerate("xyz")) for s in found
            ) <= half * half:
                return len(found)
            half *= 2

    def explain(self, kind: str, args: dict) -> list[str]:
        self.open()
        plan = self.dataset._dataset._sample_collection.database.command(
            "explain", {"aggregate": self.dataset._sample_collection_name,
                        "pipeline": [{"$match": match(kind, args)}, {"$count": "n"}],
                        "cursor": {}})
        text = repr(plan.get("queryPlanner", plan))
        return sorted(set(part.split("'")[0] for part in text.split("'stage': '")[1:]))

    def footprint(self) -> dict:
        self.open()
        db = self.fo.core.odm.get_db_conn()
        client = db.client
        client.admin.command("fsync")
        stats = db.command("dbStats")
        status = client.admin.command("serverStatus")
        return {"data_bytes": stats["dataSize"], "storage_bytes": stats["storageSize"],
                "index_bytes": stats["indexSize"], "mongod_resident_mb": status["mem"]["resident"],
                "mongod_cache_mb": round(
                    status["wiredTiger"]["cache"]["bytes currently in the cache"] / 2**20)}



def export(name: str, directory: str, limit: int) -> dict:
    import fiftyone as fo

    dataset = fo.load_dataset(name)
    baseline = rss_mb("VmRSS")
    reset_peak()
    start = time.perf_counter()
    view = dataset.sort_by("time").limit(limit)
    view.export(export_dir=directory, dataset_type=fo.types.COCODetectionDataset,
                label_field="detections", export_media=True, progress=False)
    seconds = time.perf_counter() - start
    peak = rss_mb("VmHWM")
    return {"clusters": limit, "seconds": round(seconds, 2), "baseline_rss_mb": round(baseline),
            "peak_rss_mb": round(peak), "growth_mb": round(peak - baseline)}


def serve() -> None:
    answers = os.fdopen(os.dup(sys.stdout.fileno()), "w")
    os.dup2(sys.stderr.fileno(), sys.stdout.fileno())  # FiftyOne's prints go to stderr
    side = Side(os.environ.get("FO_BENCH_DATASET", "pmem_vs_fo"))
    for line in sys.stdin:
        command = json.loads(line)
        op = command.pop("op")
        answers.write(json.dumps(getattr(side, op)(**command)) + "\n")
        answers.flush()


if __name__ == "__main__":
    if sys.argv[1:2] == ["--export"]:
        print(json.dumps(export(sys.argv[2], sys.argv[3], int(sys.argv[4]))))
    else:
        serve()
