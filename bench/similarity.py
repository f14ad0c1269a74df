"""Similarity search benchmark ("find more like this"); prints JSON.

1. Precision@10 of "same item" on the kitchen week: from every cluster of the week (or every
   n-th), `Similarity.similar_to(cluster, k=10, descriptor=[...])` as the API asks it, and the
   share of the ten found that show the same catalogue item (the three identical cups count
   as one item), per descriptor and combined (every descriptor). Also the index's build from
   MongoDB (reading and describing every cluster, crops decoded).
2. Precision on RoboSherlock's own ground truth: the PnP09 dump's persistent objects, each
   labelled with its true class (GroundTruth), imported as `pmem import` does: from each
   object that has another of its class, similar_to(k=10) per descriptor (the dump's Caffe
   CNN vectors, VFH, HS colour histograms, Hu moments) and combined. Only 9 objects of 7
   classes: two classes have two each, so each such query has exactly one right answer
   among 8 others, precision@10 is at most 0.1 and the partner's rank says more.
3. Meaning: a table of text queries on the kitchen week, each with the catalogue items it
   should find (decided from the catalogue, before running), and the share of the first ten
   results that show one of them (and the items of the first 50), spelt (today's exact and
   misspelt words) and by meaning (queries/meaning.py); the cost of a meaning query, cold
   (the model loaded) and warm, and with a vocabulary of --words more words.
4. Latency at scale: an index of N synthetic rows (random unit vectors of the largest crop
   descriptor's size, 144; four regions, two robots, a week of times) built straight into
   the index (not through MongoDB: that is 5),
   its build time and size on disk; p50/p95 of a filtered search (one region and one day:
   about 1/28 of the rows) and of an unfiltered one, and recall@10 against exact search.
   Random vectors are the hard case for a graph index; real descriptors cluster, so recall@10
   is also measured on --clustered vectors that do (20 looks of each item, two looks of one
   item ~0.6 alike).
5. Through MongoDB (--mongodb N): N clusters stored as scenes of 50 (a region, a map per
   robot, a week of times, a 144-float feature vector clustered as in 4), the index built
   from MongoDB by refresh and saved beside it (time, size), and p50/p95 of similar_to from a
   stored cluster per descriptor, unfiltered and with a filter (region, map or robot, and a
   day), hits read from MongoDB. Default 200,000. With --reuse-db NAME the database and its
   index (where `pmem serve` keeps it: PMEM_DATA_DIR/similarity/NAME) are kept: a first run
   stores and builds (a million: ~4 minutes to store, ~25 to build on two shared cores), a
   second only loads the index and times the queries (`--only mongodb` to skip the rest).
6. Ingest: storing scenes does no index work (the index catches up from MongoDB when it is
   next asked, memory/similarity.py); what it costs instead is the catch-up, measured here as
   the refresh after storing synthetic scenes in process, as the slowdown ingest would see if
   that work were done inline, and as the slowdown ingest does see while another process
   keeps an index of the same database current as `pmem serve` does (its keeper's thread, at
   PMEM_SIMILARITY_NICENESS) and asks it for more like the newest cluster twice a second (a
   user browsing a server as a robot stores scenes; --rounds of storing alone and beside it,
   alternating, each on a fresh database), with what those queries saw: their time and how
   many stored clusters they could not search yet. Meaning search does
   no ingest work either: its word vectors are computed when a query first meets a word.
   The ORB visual words of a 64 px crop (crop-orb) are timed alone, and what they would cost
   ingest if computed there (they are not: the index computes them as it catches up, the
   catalogue stage as it learns).

Usage: python bench/similarity.py [--days N] [--every N] [--vectors N] [--clustered N]
                                  [--mongodb N] [--reuse-db NAME] [--scenes N] [--words N]
                                  [--only PART ...]
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import resource
import statistics
import string
import subprocess
import sys
import tempfile
import time
from collections import Counter
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
from bson import ObjectId
from ingest import kitchen_image, scenes
from scratch import print_json, scratch_store

from percept_memory.demo import kitchen_week
from percept_memory.ingest.robosherlock import read_dump
from percept_memory.ingest.service import IngestService
from percept_memory.memory import similarity
from percept_memory.memory.schema import CLUSTERS, TERMS
from percept_memory.memory.search_keys import trigrams
from percept_memory.memory.settings import Settings, collect_less
from percept_memory.memory.similarity import Entry, RowFilter, SimilarityIndex
from percept_memory.memory.store import MemoryStore
from percept_memory.memory.types import (
    Cluster,
    FeatureVector,
    GroundTruth,
    ImageROI,
    Location,
    Scene,
)
from percept_memory.memory.types.appearance import word_counts
from percept_memory.queries import meaning
from percept_memory.queries.engine import QueryEngine
from percept_memory.queries.ops import QueryError
from percept_memory.queries.similar import Similarity

DAY = 86_400 * 10**9
WEEK_START = 1_700_000_000 * 10**9  # through_mongodb: its clusters' week
CHUNK = 50_000  # rows added to the index at a time
REGIONS = ["counter_top_sink", "counter_top_island", "table", "shelf"]
LATENCY_TARGET_MS = 10.0
LOOKS_PER_ITEM = 20  # clustered_recall: the looks of one item among the vectors
LOOK_NOISE = 0.0625  # per dimension: a look's noise has norm 0.75 against its item's 1
SLOWDOWN_TARGET = 0.10
SCENE_CLUSTERS = 50  # through_mongodb: clusters per stored scene
STORE_SCENES = 20  # through_mongodb: scenes stored per transaction
log = logging.getLogger("bench.similarity")
PNP09 = Path(__file__).resolve().parents[2] / \
    "shared/data/robosherlock/mongodump/PnP09ObjSymbolicGTFixed"
DRINKS = ["juice", "milk", "tea", "water"]
MEANINGS = {  # a text -> the catalogue items (kitchen_week.CATALOGUE) it should find
    "something to drink": DRINKS,
    "a drink": DRINKS,
    "beverages": DRINKS,
    "sweets": ["milka"],
    "something sweet": ["milka", "nutella"],
    "candy": ["milka"],
    "fruit": ["apple"],
    "crisps": ["pringles"],
    "sauce": ["ketchup"],
    "dairy": ["milk"],
    "for cleaning dishes": ["fairy", "sponge"],
    "washing-up liquid": ["fairy"],
    "tableware": ["bowl", "cup", "mug", "plate"],
    "something to eat from": ["bowl", "plate"],
}


@contextmanager
def kitchen(days: int) -> Iterator[tuple[MemoryStore, dict[ObjectId, str]]]:
    """The kitchen week in a scratch store, and cluster id -> the catalogue item it shows."""
    week = kitchen_week.generate(days=days)
    with scratch_store() as store:
        results = store.put_scenes(week.scenes)
        yield store, {cluster_id: kitchen_week.item_of(week.truth.object_at(i, j)).key
                      for i, stored in enumerate(results)
                      for j, cluster_id in enumerate(stored.cluster_ids)}


def precision(store: MemoryStore, item: dict[ObjectId, str], every: int, folder: Path) -> dict:
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
    return {"clusters": len(item), "items": len(set(item.values())),
            "observations_per_item": dict(Counter(item.values()).most_common()),
            "index_build_from_mongodb_s": round(build_s, 2),
            "index_build_clusters_per_s": round(len(item) / build_s),
            "per_descriptor": per}


def robosherlock_truth(folder: Path) -> dict:
    """Same class as RoboSherlock's ground truth says, among the PnP09 objects."""
    with scratch_store() as store:
        store.put_scenes(list(read_dump(PNP09)))
        truth = {cluster_id: annotation.class_name
                 for cluster_id, cluster in store.get_clusters(
                     [d["_id"] for d in store.clusters.find({}, {"_id": 1})]).items()
                 for annotation in cluster.annotations if isinstance(annotation, GroundTruth)}
        index = SimilarityIndex(store, folder / "robosherlock")
        index.refresh()
        search = Similarity(store, index=index)
        paired = [c for c in truth if list(truth.values()).count(truth[c]) > 1]
        per = {}
        for name in [*index.names(), "combined"]:
            chosen = [] if name == "combined" else [name]
            ranks, precisions = [], []
            for cluster_id in paired:
                try:
                    found = search.similar_to(cluster=cluster_id, k=10, descriptor=chosen).items
                except QueryError:
                    continue
                same = [truth.get(h.id) == truth[cluster_id] for h in found]
                ranks.append(same.index(True) + 1 if True in same else None)
                precisions.append(sum(same) / 10)
            per[name] = {"precision_at_10": round(float(np.mean(precisions)), 3),
                         "rank_of_the_same_class": ranks,
                         "precision_at_1": round(float(np.mean([r == 1 for r in ranks])), 3)}
    return {"objects": len(truth), "classes": len(set(truth.values())),
            "queries": len(paired), "others_per_query": len(truth) - 1,
            "best_possible_precision_at_10": 0.1, "per_descriptor": per}


def meanings(store: MemoryStore, item: dict[ObjectId, str], extra_words: int) -> dict:
    """The meaning table, then what a meaning query costs."""
    engine = QueryEngine(store)
    table, took = {}, []
    for text, expected in MEANINGS.items():
        row = {"expected": expected}
        for mode, by_meaning in (("spelt", False), ("meaning", True)):
            begin = time.perf_counter()
            found = [item[h.id] for h in engine.clusters(text=text, meaning=by_meaning,
                                                         limit=50).items]
            if by_meaning:
                took.append(time.perf_counter() - begin)
            right = sum(key in expected for key in found[:10])
            row[mode] = {"found": len(found[:10]),
                         "precision_at_10": round(right / len(found[:10]), 2) if found else None,
                         "items_in_first_10": dict(Counter(found[:10]).most_common()),
                         "items_in_first_50": dict(Counter(found).most_common())}
        row["words_meant"] = engine.runner.run(meaning.neighbours(text))
        table[text] = row
    summary = {mode: {
        "mean_precision_at_10_empty_as_0": round(float(np.mean(
            [row[mode]["precision_at_10"] or 0 for row in table.values()])), 3),
        "queries_finding_nothing": sum(not row[mode]["found"] for row in table.values())}
        for mode in ("spelt", "meaning")}
    known = set(store.db[TERMS].distinct("_id"))
    rng = np.random.default_rng(0)
    letters = np.array(list(string.ascii_lowercase))
    extra = {"".join(rng.choice(letters, int(rng.integers(4, 10)))) for _ in range(extra_words)}
    store.db[TERMS].insert_many([{"_id": w, "grams": trigrams(w)} for w in extra - known])
    large = []
    for _ in range(6):
        begin = time.perf_counter()
        engine.clusters(text="something to drink", meaning=True, limit=10)
        large.append(time.perf_counter() - begin)
    return {"queries": table, "summary": summary,
            "cost": {"vocabulary_words": len(known),
                     "first_query_s_loading_the_model": round(took[0], 3),
                     "warm_query_ms": {"p50": round(float(np.percentile(took[1:], 50)) * 1e3, 1),
                                       "p95": round(float(np.percentile(took[1:], 95)) * 1e3, 1)},
                     "with_more_words": store.db[TERMS].count_documents({}),
                     "first_query_s_embedding_them": round(large[0], 3),
                     "then_query_ms_p50": round(float(np.median(large[1:])) * 1e3, 1)}}


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
        len(loaded.rows.passing(filtered)) / count, 4)
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


def unit(rows: np.ndarray) -> np.ndarray:
    return (rows / np.linalg.norm(rows, axis=-1, keepdims=True)).astype(np.float32)


def clustered_recall(count: int, folder: Path, queries: int = 200) -> dict:
    """Recall@10 of the graph search on vectors that cluster as real descriptors do: `count`
    rows, LOOKS_PER_ITEM looks of each item (its direction plus noise: two looks of one item
    ~0.6 alike, of two items ~0), each probe a new look of an item; against exact search."""
    rng = np.random.default_rng(1)
    items = unit(rng.normal(size=(max(1, count // LOOKS_PER_ITEM), 144)))
    vectors = unit(np.repeat(items, LOOKS_PER_ITEM, axis=0)[:count]
                   + rng.normal(scale=LOOK_NOISE, size=(count, 144)))
    index = SimilarityIndex(None, folder / "clustered")  # type: ignore[arg-type]  # no MongoDB
    ids = [ObjectId() for _ in range(count)]
    start = time.perf_counter()
    for chunk in range(0, count, CHUNK):
        index.add(Entry(ids[i], i, "robot0", "table", "bench", {"crop-hog": vectors[i]})
                  for i in range(chunk, min(chunk + CHUNK, count)))
    build_s = time.perf_counter() - start
    probes = unit(items[rng.integers(len(items), size=queries)]
                  + rng.normal(scale=LOOK_NOISE, size=(queries, 144)))
    recall = []
    for probe in probes:
        exact = set(np.argsort(-(vectors @ probe))[:10].tolist())
        found = index.search({"crop-hog": probe}, 10)
        recall.append(len(exact & {index.rows.row_of[m.cluster_id] for m in found}) / 10)
    return {"vectors": count, "looks_per_item": LOOKS_PER_ITEM, "build_s": round(build_s, 1),
            "recall_at_10_unfiltered": round(float(np.mean(recall)), 3)}


def stored_for_scale(store: MemoryStore, count: int) -> float:
    """Store clusters as scenes (SCENE_CLUSTERS each; a region, a map per robot, a week of
    times, a 144-float feature vector that clusters as in clustered_recall) until the database
    holds `count`; a kept database is filled where its last run stopped. Returns the seconds."""
    items = unit(np.random.default_rng(2).normal(size=(max(1, count // LOOKS_PER_ITEM), 144)))
    have = store.clusters.estimated_document_count()
    rng = np.random.default_rng([2, have])
    robots = ["robot0", "robot1"]
    start = time.perf_counter()
    for first in range(have, count, SCENE_CLUSTERS * STORE_SCENES):
        batch = []
        for s in range(first, min(first + SCENE_CLUSTERS * STORE_SCENES, count), SCENE_CLUSTERS):
            size = min(SCENE_CLUSTERS, count - s)
            looks = unit(items[rng.integers(len(items), size=size)]
                         + rng.normal(scale=LOOK_NOISE, size=(size, 144)))
            region = REGIONS[int(rng.integers(len(REGIONS)))]
            batch.append(Scene(
                timestamp=int(rng.integers(0, 7 * DAY)) + WEEK_START,
                robot=robots[s // SCENE_CLUSTERS % 2],
                clusters=[Cluster(annotations=[
                    Location(region=region, position=tuple(rng.uniform(0, 3, 3))),
                    FeatureVector(name="cnn", vector=look)]) for look in looks]))
        store.put_scenes(batch)
        if (first // (SCENE_CLUSTERS * STORE_SCENES)) % 50 == 0:
            log.info("stored %d clusters of %d", first + SCENE_CLUSTERS * STORE_SCENES, count)
    return time.perf_counter() - start


def through_mongodb(count: int, folder: Path, keep: str | None, queries: int = 200) -> dict:
    """The scale figures through the user's path: `count` clusters in MongoDB
    (stored_for_scale), the index built from MongoDB by refresh (read, decoded, described,
    added, saved beside the database), then p50/p95 of Similarity.similar_to from a stored
    cluster, hits read back from MongoDB, per descriptor, unfiltered and with a filter (one
    region, one map or one robot, and one day), and of the index's search alone. With `keep`,
    that database is kept (filled only up to `count`) and its index is the one `pmem serve`
    would use (PMEM_DATA_DIR/similarity/<keep>), kept too: a second run only loads it."""
    with scratch_store(keep) as store:
        store_s = stored_for_scale(store, count)
        stored = time.perf_counter()
        index = SimilarityIndex.of(store, Settings(db=keep)) if keep else \
            SimilarityIndex(store, folder / "mongodb")
        built = not (index.folder / "rows.json").exists()
        start = time.perf_counter()
        index.refresh()  # and saves what it added
        build_s = time.perf_counter() - start
        size = sum(f.stat().st_size for f in index.folder.iterdir())
        start = time.perf_counter()
        loaded = SimilarityIndex(store, index.folder)
        loaded.refresh()  # loads the files, then finds nothing to add
        load_s = time.perf_counter() - start
        del index
        # A refresh reads again the ids made within the margin before its last read (they may
        # not have been committed then): those of the last seconds of storing, until then.
        time.sleep(max(0.0, similarity.MARGIN.total_seconds() - (time.perf_counter() - stored)))
        loaded.refresh()
        start = time.perf_counter()  # what the first filtered query after the load pays
        laid = [v.laid(loaded.rows.passing(RowFilter(after=0)).layout)
                for v in loaded.vectors.values()]
        layout_s = time.perf_counter() - start
        latency = scale_latency(store, loaded, queries)
    per_million = 1e6 / count
    p95 = max(row["similar_to_p95_ms"] for per in latency.values()
              for name, row in per.items() if name != "unfiltered")
    return {"clusters": count, "dimensions": 144, "clusters_per_scene": SCENE_CLUSTERS,
            "database": keep, "store_s": round(store_s, 1),
            "index_built_now": built, "index_folder": str(loaded.folder),
            "index_build_from_mongodb_s" if built else "index_found_and_loaded_s":
                round(build_s, 1),
            "index_build_clusters_per_s": round(count / build_s) if built else None,
            "index_load_s": round(load_s, 2), "index_size_mb": round(size / 2**20, 1),
            "rows_laid_out_s": round(layout_s, 2),  # sorted by robot, map and time
            "int8_copies_mb": round(sum(  # in memory only, beside the files' size: by row and
                v.steps.nbytes + v.sizes.nbytes for v in loaded.vectors.values())  # laid out
                / 2**20 + sum(c.steps.nbytes + c.sizes.nbytes for c in laid) / 2**20, 1),
            "process_peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
                                         / 1024),
            "per_million_linear_extrapolation": None if count >= 1_000_000 or not built else {
                "index_build_s": round(build_s * per_million),
                "index_size_mb": round(size / 2**20 * per_million)},
            "latency": latency, "load_average": os.getloadavg(),
            "target_p95_ms": LATENCY_TARGET_MS, "met": p95 < LATENCY_TARGET_MS}


def scale_latency(store: MemoryStore, index: SimilarityIndex, queries: int) -> dict:
    """Per descriptor and filter: p50/p95 of similar_to as a server answers it (its keeper's
    thread asked to catch up, start read from MongoDB, search, hits read back) and p95 of the
    index's search alone, from `queries` stored clusters."""
    rng = np.random.default_rng(3)
    search = Similarity(store, index=index, in_background=True)
    starts = [index.rows.ids[i] for i in rng.integers(len(index.rows), size=queries)]
    day = {"after": WEEK_START + 2 * DAY, "before": WEEK_START + 3 * DAY - 1}
    filters = {"unfiltered": {}, "region_and_day": {"region": ["table"], **day},
               "map_and_day": {"map": ["robot1/map"], **day},
               "robot_and_day": {"robot": ["robot0"], **day}}
    latency: dict = {}
    for descriptor in index.names():
        for name, where in filters.items():
            took, alone = [], []
            for cluster_id in starts:
                begin = time.perf_counter()
                search.similar_to(cluster=cluster_id, k=10, descriptor=[descriptor], **where)
                took.append(time.perf_counter() - begin)
                vector = {descriptor: index.descriptors_of(cluster_id)[descriptor]}
                begin = time.perf_counter()
                index.search(vector, 10, RowFilter(**where), [cluster_id])
                alone.append(time.perf_counter() - begin)
            latency.setdefault(descriptor, {})[name] = {
                "share_of_rows": round(len(index.rows.passing(RowFilter(**where)))
                                       / len(index.rows), 4),
                "similar_to_p50_ms": round(float(np.percentile(took, 50)) * 1e3, 2),
                "similar_to_p95_ms": round(float(np.percentile(took, 95)) * 1e3, 2),
                "index_search_p50_ms": round(float(np.percentile(alone, 50)) * 1e3, 2),
                "index_search_p95_ms": round(float(np.percentile(alone, 95)) * 1e3, 2)}
    search.close()
    return latency


def orb_cost(crops: list[np.ndarray]) -> dict:
    """What the visual words of one crop cost (ORB and the nearest words), p50 and p95."""
    took = []
    for crop in crops:
        begin = time.perf_counter()
        word_counts(crop)
        took.append(time.perf_counter() - begin)
    return {"crops": len(crops), "p50_us": round(float(np.percentile(took, 50)) * 1e6),
            "p95_us": round(float(np.percentile(took, 95)) * 1e6)}


def ingest_cost(count: int, folder: Path, rounds: int = 5) -> dict:
    """What the index costs ingest: nothing in the storing itself; the catch-up a query then
    does (timed, and as a share of ingest if it were done inline); and ingest's rate alone
    against beside a process that keeps its own index of the same database current and asks
    it for more like the newest cluster twice a second, as a server does for a user browsing
    while a robot stores scenes (the two cores shared; rounds alternating, each on a fresh
    database, as the machine's speed drifts)."""
    image = kitchen_image()
    generated = scenes(count, 1_700_000_000_000_000_000, image, seed=1)
    crops = [h.crop.data for s in generated for c in s.clusters for h in c.hypotheses
             if isinstance(h, ImageROI) and h.crop is not None]
    visual_words = orb_cost(crops)
    with scratch_store() as store:
        index = SimilarityIndex(store, folder / "ingest")
        index.refresh()
        ingest_s = stored_s(store, generated)
        start = time.perf_counter()
        added = index.refresh()
        refresh_s = time.perf_counter() - start
        start = time.perf_counter()
        index.refresh()
        again_s = time.perf_counter() - start
    rates: dict[str, list[float]] = {"alone": [], "beside_queries": []}
    # CPU seconds spent while the scenes were stored, per round: by ingest's process, by
    # mongod, by the follower (its keeper, mostly)
    spent: dict[str, list[dict]] = {way: [] for way in rates}
    asked: list[dict] = []  # the follower's queries while scenes were stored
    current_again_s: list[float] = []  # from the end of storing to the follower's first answer
    # that searched every stored cluster
    for number in range(rounds):
        for way, rate in rates.items():
            with scratch_store() as store:
                follower = None if way == "alone" else subprocess.Popen(
                    [sys.executable, __file__, "--follow", store.db.name,
                     str(folder / f"follow-{number}")], stdout=subprocess.PIPE, text=True)
                if follower and follower.stdout.readline().strip() != "following":
                    raise RuntimeError("the follower did not start (its error is above)")
                processes = {"mongod": store.client.admin.command("serverStatus")["pid"],
                             **({"follower": follower.pid} if follower else {})}
                before = {name: cpu_s(pid) for name, pid in processes.items()}
                ingest_cpu = time.process_time()
                rate.append(added / stored_s(store, generated))
                spent[way].append({"ingest": time.process_time() - ingest_cpu,
                                   **{name: cpu_s(pid) - before[name]
                                      for name, pid in processes.items()}})
                if follower:
                    stored_at = time.time()
                    answers = list(answers_until_current(follower, stored_at))
                    current_again_s.append(answers[-1]["at"] + answers[-1]["ms"] / 1e3
                                           - stored_at)
                    follower.terminate()
                    follower.communicate(timeout=30)
                    asked += [q for q in answers if q["at"] < stored_at]
    slowdown = 1 - statistics.median(rates["beside_queries"]) / statistics.median(
        rates["alone"])
    waits = [q["ms"] for q in asked]
    behind = [q["not_indexed_yet"] for q in asked]
    inline = refresh_s / ingest_s
    orb_s = visual_words["p50_us"] * len(crops) / 1e6
    return {"scenes": count, "clusters": added, "rounds": rounds,
            "ingest_clusters_per_s": {way: [round(r) for r in rate]
                                      for way, rate in rates.items()},
            "ingest_slowdown_beside_queries": round(slowdown, 3),
            "target_slowdown": SLOWDOWN_TARGET, "met": slowdown <= SLOWDOWN_TARGET,
            "keeper_niceness": Settings().similarity_niceness,
            "cpu_s_while_storing_median": {
                way: {name: round(statistics.median(r[name] for r in rounds_spent), 2)
                      for name in rounds_spent[0]} for way, rounds_spent in spent.items()},
            "queries_during_ingest": {  # what the follower's user saw meanwhile
                "count": len(asked),
                "ms": {"p50": round(float(np.percentile(waits, 50)), 1),
                       "p95": round(float(np.percentile(waits, 95)), 1)} if asked else None,
                "share_not_current": round(float(np.mean(np.array(behind) > 0)), 2)
                if asked else None,
                "not_indexed_yet_max": max(behind, default=None)},
            # after each round: how long until the follower's index searched every cluster
            "current_again_s_after_storing": {
                "median": round(statistics.median(current_again_s), 1),
                "max": round(max(current_again_s), 1)} if current_again_s else None,
            "visual_words_per_64px_crop": visual_words,
            "visual_words_slowdown_if_at_ingest": round(orb_s / ingest_s, 3),
            "visual_words_share_of_catch_up": round(orb_s / refresh_s, 3),
            "catch_up_s": round(refresh_s, 2),
            "catch_up_clusters_per_s": round(added / refresh_s),
            "slowdown_if_inline": round(inline, 3),
            # the next refresh reads the ids of the last MARGIN seconds again (similarity.py)
            "refresh_right_after_ms": round(again_s * 1e3, 1)}


def answers_until_current(follower: subprocess.Popen, stored_at: float,
                          timeout: float = 300.0) -> Iterator[dict]:
    """The follower's answers (a JSON line each), up to the first one asked after `stored_at`
    that searched every stored cluster."""
    for line in follower.stdout:
        answer = json.loads(line)
        yield answer
        if answer["at"] >= stored_at and answer["not_indexed_yet"] == 0:
            return
        if answer["at"] - stored_at > timeout:
            raise RuntimeError(f"the follower's index was not current {timeout:.0f} s after")
    raise RuntimeError("the follower stopped (its error is above)")


def cpu_s(pid: int) -> float:
    """CPU seconds a process has used so far, all its threads (Linux's /proc)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def stored_s(store: MemoryStore, generated: list[Scene]) -> float:
    """Seconds to store the scenes in process, in batches of 32 (as bench/ingest.py does)."""
    service = IngestService(store, batch_size=32)
    start = time.perf_counter()
    for _ in service.ingest_stream((str(i), s) for i, s in enumerate(generated)):
        pass
    return time.perf_counter() - start


def follow(db: str, folder: str) -> None:
    """(--follow) A user browsing a server while scenes are stored: its index kept current as
    `pmem serve` keeps it and asked for more like the newest cluster twice a second, until
    terminated; a line of JSON per query (when asked, its time, the clusters it could not search
    yet)."""
    settings = Settings(db=db)
    store = MemoryStore.open(settings)
    search = Similarity(store, settings, SimilarityIndex(store, Path(folder)),
                        in_background=True)
    search.index.refresh()
    print("following", flush=True)
    while True:
        newest = store.db[CLUSTERS].find_one({}, {"_id": 1}, sort=[("_id", -1)])
        if newest is not None:
            at, start = time.time(), time.perf_counter()
            page = search.similar_to(cluster=newest["_id"], k=10)
            print(json.dumps({"at": at, "ms": (time.perf_counter() - start) * 1e3,
                              "not_indexed_yet": page.not_indexed_yet}), flush=True)
        time.sleep(0.5)


PARTS = ("kitchen", "robosherlock", "meaning", "scale", "clustered", "mongodb", "ingest")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--days", type=int, default=7)
    parser.add_argument("--every", type=int, default=3, help="query from every n-th cluster")
    parser.add_argument("--vectors", type=int, default=1_000_000)
    parser.add_argument("--clustered", type=int, default=200_000,
                        help="vectors of the recall check on clustered data (0: skip)")
    parser.add_argument("--mongodb", type=int, default=200_000,
                        help="clusters stored for the figures through MongoDB (0: skip)")
    parser.add_argument("--reuse-db", metavar="NAME", help=(
        "through MongoDB on this database, kept with its index (filled up to --mongodb "
        "clusters when it holds fewer; the index built only when it has none)"))
    parser.add_argument("--only", nargs="+", choices=PARTS, default=PARTS,
                        help="run only these parts")
    parser.add_argument("--scenes", type=int, default=1000,
                        help="ingest: scenes stored per round (6 clusters each)")
    parser.add_argument("--words", type=int, default=50_000,
                        help="words added to the vocabulary to see what a large one costs")
    parser.add_argument("--rounds", type=int, default=5,
                        help="ingest: rounds of storing alone and beside queries")
    parser.add_argument("--follow", nargs=2, metavar=("DB", "FOLDER"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.follow:
        return follow(*args.follow)  # until terminated
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    collect_less()
    wanted = set(args.only)
    result: dict = {"benchmark": "similarity"}
    with tempfile.TemporaryDirectory() as name:
        folder = Path(name)
        if wanted & {"kitchen", "meaning"}:
            with kitchen(args.days) as (store, item):
                if "kitchen" in wanted:
                    result["kitchen_week"] = {"days": args.days,
                                              **precision(store, item, args.every, folder)}
                if "meaning" in wanted:
                    result["meaning"] = meanings(store, item, args.words)
        if "robosherlock" in wanted:
            result["robosherlock_ground_truth"] = robosherlock_truth(folder)
        if "scale" in wanted:
            result["at_scale"] = at_scale(args.vectors, folder)
        if "clustered" in wanted and args.clustered:
            result["clustered_recall"] = clustered_recall(args.clustered, folder)
        if "mongodb" in wanted and args.mongodb:
            result["through_mongodb"] = through_mongodb(args.mongodb, folder, args.reuse_db)
        if "ingest" in wanted:
            result["ingest"] = ingest_cost(args.scenes, folder, args.rounds)
    print_json(result)


if __name__ == "__main__":
    main()
