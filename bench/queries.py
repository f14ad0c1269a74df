"""Query benchmark at scale; prints JSON: p50 / p95 latency per query type.

Builds a memory of --clusters clusters (default 1,000,000) in a scratch database: a building
of 50 kitchens (200 regions on a 10 m grid), 5,000 objects of the kitchen week's kinds seen
over a year, one observation every ~30 s, objects moved now and then. Cluster documents are
the kitchen week's own, as documents.py lays them out (search keys included), with new ids,
times, objects and positions; their image crops and colour histograms are left out to keep
the build small (no query reads them). `objects` and `events` are the belief state such a
year gives (appear, stay, move). Documents are inserted prepared, in bulk.

Then each query type runs --samples times with random arguments through QueryEngine.
Targets (p95): text < 50 ms, 3D box / sphere / kNN < 20 ms, time range < 20 ms,
where_was < 100 ms. The winning plan of one sample per type is reported too.

Usage: python bench/queries.py [--clusters N] [--samples N] [--keep DB]
(uses MONGODB_URI or the embedded mongod; --keep DB builds into DB once and reuses it)
"""

from __future__ import annotations

import argparse
import statistics
import time

import bson
import numpy as np
from bson import ObjectId
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from scratch import footprint, print_json, scratch_store

from percept_memory.demo import kitchen_week as kw
from percept_memory.memory import documents, search_keys
from percept_memory.memory.schema import CLUSTERS, EVENTS, MAPS, OBJECTS
from percept_memory.memory.store import MemoryStore, vocabulary_upserts
from percept_memory.memory.types import Scene
from percept_memory.queries.engine import QueryEngine

KITCHENS = 50
OBJECTS_PER_KITCHEN = 100
SECONDS_PER_CLUSTER = 30
START = kw.timestamp_from_datetime(kw.START)
TARGETS_MS = {"text": 50, "text_misspelt": 50, "box": 20, "sphere": 20, "knn": 20,
              "time_range": 20, "where_was": 100}


def templates() -> dict[str, list[dict]]:
    """Cluster documents of the kitchen week by catalogue kind, without crops and histograms."""
    week = kw.generate(days=2)
    for scene in week.scenes:
        scene.ensure_id()
    written = documents.scene_documents(week.scenes, threshold=2**30)
    kinds: dict[str, list[dict]] = {}
    truth = [o for scene in week.truth.scenes for o in scene.objects]
    for raw, object_id in zip(written.clusters, truth, strict=True):
        doc = bson.decode(raw.raw)
        doc.pop("hypotheses", None)
        doc.pop(documents.BLOBS_KEY, None)
        doc["annotations"] = [a for a in doc["annotations"]
                              if a["_type"] != "pm.annotation.ColorHistogram"]
        kinds.setdefault(object_id.partition("#")[0], []).append(doc)
    return kinds


class World:
    """Where each object is, and the belief state a year of looking gives."""

    def __init__(self, rng: np.random.Generator, kinds: list[str]):
        self.rng = rng
        self.regions = [(k, name, region) for k in range(KITCHENS)
                        for name, region in kw.REGIONS.items()]
        count = KITCHENS * OBJECTS_PER_KITCHEN
        self.kind = [kinds[i % len(kinds)] for i in range(count)]
        self.ids = [ObjectId() for _ in range(count)]
        self.place = [self._spot(int(rng.integers(len(self.regions)))) for _ in range(count)]
        self.seen = [0] * count

    def region_name(self, index: int) -> str:
        kitchen, name, _ = self.regions[index]
        return f"k{kitchen}_{name}"

    def _spot(self, index: int) -> tuple[int, tuple[float, float, float]]:
        kitchen, _, region = self.regions[index]
        offset = (kitchen % 10) * 10.0, (kitchen // 10) * 10.0
        x = self.rng.uniform(*region.x) + offset[0]
        y = self.rng.uniform(*region.y) + offset[1]
        return index, (round(x, 4), round(y, 4), region.z + 0.05)

    def observe(self, o: int) -> str:
        """Look at object o: it may have been moved since. Returns the event's explanation."""
        if not self.seen[o]:
            explanation = "appear"
        elif self.rng.random() < 0.05:
            self.place[o] = self._spot(int(self.rng.integers(len(self.regions))))
            explanation = "move"
        else:
            explanation = "stay"
        self.seen[o] += 1
        return explanation

MAP = "building"  # the map of the built memory's objects and events

def build(store: MemoryStore, count: int, progress: Progress, batch: int = 5000) -> World:
    rng = np.random.default_rng(5)
    kinds = templates()
    world = World(rng, sorted(kinds))
    searches = [doc["search"] for docs in kinds.values() for doc in docs]
    vocabulary = documents.vocabulary_documents({t for s in searches for t in s["terms"]},
                                                {label for s in searches for label in s["labels"]})
    for collection, entries in vocabulary.items():
        store.db[collection].bulk_write(vocabulary_upserts(entries))
    for collection in (CLUSTERS, EVENTS):  # indexes are built after the bulk load: faster
        store.db[collection].drop_indexes()
    task = progress.add_task("clusters", total=count)
    last: dict[int, dict] = {}
    for start in range(0, count, batch):
        clusters, events = [], []
        for i in range(start, min(count, start + batch)):
            o = int(rng.integers(len(world.ids)))
            explanation = world.observe(o)
            region, spot = world.place[o]
            position = [round(v + float(rng.normal(0, 0.01)), 4) for v in spot]
            template = kinds[world.kind[o]][i % len(kinds[world.kind[o]])]
            t = START + i * SECONDS_PER_CLUSTER * kw.SECOND + int(rng.integers(kw.SECOND))
            cluster_id, scene_id = ObjectId(), ObjectId()
            search = {**template["search"], "time": t, "robot": "pr2",
                      "region": world.region_name(region), **search_keys.place(position)}
            clusters.append({**template, "_id": cluster_id, "scene_id": scene_id,
                             "object_id": world.ids[o], "search": search})
            event = {"map": MAP, "object_id": world.ids[o], "scene_id": scene_id,
                     "cluster_id": cluster_id, "time": t, "robot": "pr2",
                     "explanation": explanation,
                     "probability": 0.9, "alternatives": [], "position": position,
                     "region": search["region"]}
            events.append(event)
            last[o] = {**event, "names": template["search"]["labels"][:3]}
        store.clusters.insert_many(clusters, ordered=False)
        store.db[EVENTS].insert_many(events, ordered=False)
        progress.advance(task, len(clusters))
    store.db[OBJECTS].insert_many([
        {"_id": world.ids[o], "name": e["names"][0] if e["names"] else None,
         "names": e["names"], "label_weights": {}, "state": "present", "first_seen": START,
         "last_seen": e["time"], "last_scene": e["scene_id"], "last_cluster": e["cluster_id"],
         "position": e["position"], "x": e["position"][0], "y": e["position"][1], "map": MAP,
         "region": e["region"], "robot": "pr2", "observations": world.seen[o]}
        for o, e in last.items()])
    # the map's first and last scene (its time span) and its belief's entry, as a map has them
    store.put_scenes([Scene(timestamp=START + i * count * SECONDS_PER_CLUSTER * kw.SECOND,
                            robot="pr2", map=MAP) for i in (0, 1)])
    store.db[MAPS].update_one({"_id": MAP}, {"$set": {"consolidated": None}}, upsert=True)
    indexing = progress.add_task("indexes", total=None)
    store.prepare()
    progress.update(indexing, total=1, completed=1)
    return world


def samples(world: World, count: int, rng: np.random.Generator, words: list[str],
            objects: list[ObjectId]) -> dict:
    """Random arguments for each query type."""
    end = START + count * SECONDS_PER_CLUSTER * kw.SECOND

    def spot():
        return world.place[int(rng.integers(len(world.place)))][1]

    def moment():
        return int(rng.integers(START, end))

    def misspelt(word: str) -> str:
        i = int(rng.integers(1, len(word) - 1))
        return word[:i] + word[i + 1:]

    long_words = [w for w in words if len(w) >= 6]
    return {
        "text": lambda: ("clusters", {"text": str(rng.choice(words)), "limit": 20}),
        "text_misspelt": lambda: ("clusters", {"text": misspelt(str(rng.choice(long_words))),
                                               "limit": 20}),
        "box": lambda: ("clusters", {"box": _box(spot(), rng.uniform(0.2, 1.0)), "limit": 50}),
        "sphere": lambda: ("clusters", {"sphere": {"center": spot(),
                                                   "radius": rng.uniform(0.1, 0.5)},
                                        "limit": 50}),
        "knn": lambda: ("clusters", {"near": spot(), "k": 10}),
        "time_range": lambda: ("clusters", {"after": (t := moment()),
                                            "before": t + 3600 * kw.SECOND, "limit": 50}),
        "region_time": lambda: ("clusters", {"region": world.region_name(
            int(rng.integers(len(world.regions)))), "before": moment(), "limit": 50}),
        "field_predicate": lambda: ("clusters", {"where": "classification:confidence>0.9",
                                                 "after": moment(), "limit": 50}),
        "where_is": lambda: ("where_is", {"x": str(rng.choice(long_words))}),
        "where_was": lambda: ("where_was", {"x": str(objects[int(rng.integers(
            len(objects)))])}),
        "what_is_at": lambda: ("what_is_at", {"region": world.region_name(
            int(rng.integers(len(world.regions)))), "t": moment()}),
        "changes": lambda: ("changes", {"region": world.region_name(
            int(rng.integers(len(world.regions)))), "t1": (t := moment()),
            "t2": t + 86400 * kw.SECOND}),
    }


def _box(centre, half: float) -> str:
    return ",".join(str(v) for v in (*(c - half for c in centre), *(c + half for c in centre)))


def measure(store: MemoryStore, world: World, clusters: int, count: int,
            progress: Progress) -> dict:
    rng = np.random.default_rng(11)
    words = sorted(doc["_id"] for doc in store.db["terms"].find({}, {"_id": 1}))
    engine = QueryEngine(store)
    results = {}
    objects = [doc["_id"] for doc in store.db[OBJECTS].find({}, {"_id": 1})]
    kinds = samples(world, clusters, rng, words, objects)
    task = progress.add_task("queries", total=count * len(kinds))
    for kind, make in kinds.items():
        for _ in range(5):  # warm up
            name, query = make()
            getattr(engine, name)(**query)
        times = []
        for _ in range(count):
            name, query = make()
            start = time.perf_counter()
            getattr(engine, name)(**query)
            times.append((time.perf_counter() - start) * 1000)
            progress.advance(task)
        plans: list = []
        getattr(QueryEngine(store, explain=plans), name)(**query)
        p95 = float(np.percentile(times, 95))
        results[kind] = {
            "p50_ms": round(statistics.median(times), 2), "p95_ms": round(p95, 2),
            **({"target_p95_ms": TARGETS_MS[kind], "met": p95 < TARGETS_MS[kind]}
               if kind in TARGETS_MS else {}),
            "indexes": sorted({f"{p['collection']}.{i}" for p in plans for i in p["indexes"]}),
            "collscan": any("COLLSCAN" in p["stages"] for p in plans),
        }
    return results


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--clusters", type=int, default=1_000_000)
    parser.add_argument("--samples", type=int, default=200)
    parser.add_argument("--keep", metavar="DB", help="build into DB (once) and keep it")
    args = parser.parse_args()
    with scratch_store(args.keep) as store, Progress(
            TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
            TimeElapsedColumn(), console=Console(stderr=True), transient=True) as progress:
        start = time.perf_counter()
        reuse = args.keep and store.clusters.estimated_document_count() == args.clusters
        if reuse:
            world = World(np.random.default_rng(5), sorted(templates()))
            world.place = [(0, tuple(doc["position"])) for doc in
                           store.db[OBJECTS].find({}, {"position": 1})]
        else:
            world = build(store, args.clusters, progress)
        built = time.perf_counter() - start
        result = {
            "benchmark": "queries",
            "clusters": store.clusters.estimated_document_count(),
            "events": store.db[EVENTS].estimated_document_count(),
            "objects": store.db[OBJECTS].estimated_document_count(),
            "build_s": None if reuse else round(built, 1),
            "samples_per_type": args.samples,
            "queries": measure(store, world, args.clusters, args.samples, progress),
            "footprint": footprint(store),
        }
    print_json(result)


if __name__ == "__main__":
    main()
