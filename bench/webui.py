"""Server render time of the HTML pages; prints JSON.

A scene of 20 clusters (x 20 annotations, 64 px crops cut from the real kitchen frame, the
frame itself and its depth as the scene images) and 200 more scenes for the scene log, in a
scratch database on the configured or embedded mongod, dropped afterwards. Pages are fetched
in-process through the ASGI app (no network), so the time is reading + rendering. Target:
scene page < 200 ms.

The map page over the kitchen week (--map-days days, consolidated), at its end and midway.

Then the search page over a large memory: --search-clusters clusters (default 1,000,000)
built as bench/queries.py builds them (a building of 50 kitchens, a year of observations),
searched by text, region and time, a sphere, an annotation field predicate, as a grid and as
a list, and its second page; and the map page of its one map of 5,000 objects, whole and
zoomed, now and midway through its year, with each page's size. --keep DB builds into DB once
and reuses it (bench/queries.py --keep DB builds the same).

Then the 3D view of the real RGB-D kitchen frame (its page and its 200,000 points), and the
playback over a robot's --playback-scenes scenes (default 1,000,000, a year, one in 1,000 with
an annotator's error, an object with an event in one in 100): the API's steps and the page.

Then the annotators page over --annotator-clusters clusters (default 1,000,000) in scenes of
the kitchen week's (a scene a minute, ~5 clusters each, their logs; each cluster also named by
a detector, one in five with its ground truth): the page over the latest 500 and 5,000
scenes, over 500 scenes midway, a confusion cell's list of clusters, and the JSON API.

Then the scene log's facet counts over --facet-scenes scenes (default 200,000: as many as
1,000,000 clusters of 5 make).

Usage: python bench/webui.py [--repeat N] [--map-days N] [--search-clusters N] [--keep DB]
                             [--playback-scenes N] [--annotator-clusters N] [--facet-scenes N]
                             [--only SECTION]
(--search-clusters 0: no search pages; --only, repeatable: just those sections)
"""

from __future__ import annotations

import argparse
import html
import re
import statistics
import time
from urllib.parse import urlencode

import bson
import cv2
import numpy as np
from bson import ObjectId
from fastapi.testclient import TestClient
from ingest import KITCHEN, kitchen_image  # bench/ingest.py, beside this file
from queries import MAP, build  # bench/queries.py
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from scratch import print_json, scratch_store

from percept_memory.demo import kitchen_week
from percept_memory.ingest import synthetic
from percept_memory.ingest.rgbd import read_samples
from percept_memory.ingest.service import IngestService
from percept_memory.memory import documents
from percept_memory.memory.schema import CLUSTERS, SCENES
from percept_memory.memory.settings import Settings
from percept_memory.memory.types import Image, LogLine, Scene, datetime_from_timestamp
from percept_memory.webui.app import create_app
from percept_memory.webui.facets import facet_counts
from percept_memory.webui.histogram import scene_histogram
from percept_memory.webui.scene_log import CHOICES, scene_filter

STAMP = 1_700_000_000_000_000_000
BATCH = 25  # scenes a transaction: a small embedded mongod's cache refuses 200 with crops


def timed(client: TestClient, path: str, repeat: int) -> dict:
    client.get(path).raise_for_status()  # warm
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        client.get(path).raise_for_status()
        times.append((time.perf_counter() - start) * 1000)
    times.sort()
    return {"median_ms": round(statistics.median(times), 1),
            "p95_ms": round(times[int(0.95 * (len(times) - 1))], 1)}


SEARCHES = {
    "newest": {},
    "text": {"text": "cereal"},
    "text_list": {"text": "cereal", "view": "list"},
    "region_time": {"region": "k7_shelf", "after": "2024-06-01T00:00",
                    "before": "2024-06-08T00:00"},
    "sphere": {"sphere": "71.9,30.2,1.25,0.5"},
    "predicate": {"where": "classification:confidence>0.9", "region": "k3_table"},
}


def search_facets(page: str) -> dict:
    """The hits on a search page, and how many of the regions and robots it offers have a
    count."""
    found = {"hits": page.count('class="hit"')}
    for name in ("region", "robot"):
        select = re.search(rf'<select name="{name}".*?</select>', page, re.S).group(0)
        offered = re.findall(r"<option value=\"[^\"]+\"", select)  # (not "any robot")
        found[f"{name}s_counted"] = len(re.findall(r"\([\d,]+\+?\)</option>", select))
        found[f"{name}s"] = len(offered)
    return found


def search_pages(args: argparse.Namespace, big: Scene) -> dict:
    """Render times of the search page over a memory of args.search_clusters clusters, and of
    the scene viewer, its 3D view and a cluster page of `big` stored in that memory."""
    with scratch_store(args.keep) as store:
        start = time.perf_counter()
        reuse = args.keep and store.clusters.estimated_document_count() == args.search_clusters
        if not reuse:
            with Progress(TextColumn("[bold]{task.description}"), BarColumn(),
                          MofNCompleteColumn(), TimeElapsedColumn(),
                          console=Console(stderr=True), transient=True) as progress:
                build(store, args.search_clusters, progress)
        built = time.perf_counter() - start
        client = TestClient(create_app(store, Settings(db=store.db.name)),
                            base_url="http://127.0.0.1")
        pages = {name: {**timed(client, path := "/search?" + urlencode(query), args.repeat),
                        **search_facets(client.get(path).text)}
                 for name, query in SEARCHES.items()}
        first = client.get("/search?text=cereal").text
        second = html.unescape(re.search(r'class="next" href="([^"]+)"', first).group(1))
        pages["text_second_page"] = timed(client, second, args.repeat)
        in_memory = None
        if not args.keep:  # (a kept memory stays as bench/queries.py builds it)
            store.put_scenes([big])
            in_memory = {"scene_page_20_clusters": timed(client, f"/scenes/{big.id}",
                                                         args.repeat),
                         "scene_page_3d": timed(client, f"/scenes/{big.id}?view=3d",
                                                args.repeat),
                         "cluster_page": timed(client, f"/clusters/{big.clusters[0].id}",
                                               args.repeat)}
        return {"clusters": store.clusters.estimated_document_count(),
                "build_s": None if reuse else round(built, 1), "pages": pages,
                "scene_pages_in_this_memory": in_memory,
                "map_pages": map_pages_of(store, client, args.repeat)}


def map_pages_of(store, client: TestClient, repeat: int) -> dict:
    """The map page of the large memory's one map (its 50 kitchens' objects): whole and
    zoomed into one kitchen (a 10 m square) and one counter of it, now and midway through
    the year; each with the page's size and how many objects, markers and table rows it
    draws."""
    first, last = (store.scenes.find_one({"map": MAP}, sort=[("timestamp", order)])["timestamp"]
                   for order in (1, -1))
    midway = {"at": (first + last) // 2 // 10**9}
    views = {"whole": {}, "kitchen": {"box": "0,0,10,10"}, "counter": {"box": "0,0,2,2"}}
    out = {}
    for name, view in views.items():
        for when, moment in (("now", {}), ("midway", midway)):
            path = "/map?" + urlencode({"map": MAP, **view, **moment})
            body = client.get(path).text
            out[f"{name}_{when}"] = {
                **timed(client, path, repeat), "kb": round(len(body.encode()) / 1024, 1),
                "objects_drawn": body.count('class="object '),
                "markers": len(re.findall(r'class="marker[^"]*" data-count', body)),
                "table_rows": body.count("<tr") - 1}
    return out


def map_page(args: argparse.Namespace) -> dict:
    """Render times of the map page over the consolidated kitchen week."""
    week = kitchen_week.generate(days=args.map_days)
    with scratch_store() as store:
        service = IngestService(store)
        list(service.ingest_stream((str(i), scene) for i, scene in enumerate(week.scenes)))
        service.pipeline.drain(timeout=1800)
        client = TestClient(create_app(store, Settings(db=store.db.name)),
                            base_url="http://127.0.0.1")
        midway = week.scenes[len(week.scenes) // 2].timestamp // 10**9
        return {"scenes": len(week.scenes), "objects": store.db.objects.count_documents({}),
                "now": timed(client, f"/map?map={kitchen_week.MAP}", args.repeat),
                "midway": timed(client, f"/map?map={kitchen_week.MAP}&at={midway}",
                                args.repeat)}


def solid_views(repeat: int) -> dict:
    """The 3D view of the real RGB-D kitchen frame: the page, and its points as binary."""
    (scene,) = read_samples(KITCHEN)
    with scratch_store() as store:
        store.put_scenes([scene])
        client = TestClient(create_app(store, Settings(db=store.db.name, consolidator=False)),
                            base_url="http://127.0.0.1")
        return {"scene_page_3d": timed(client, f"/scenes/{scene.id}?view=3d", repeat),
                "cloud_200k_points": timed(client, f"/api/scenes/{scene.id}/cloud", repeat)}


def playback(count: int, repeat: int) -> dict:
    """The playback's steps over `count` scenes of one robot in one map, a year long."""
    step = 365 * 86_400 * 10**9 // count
    with scratch_store() as store:
        fine, failed = (Scene(timestamp=STAMP + i, robot="pr2", map="site", log=log)
                        for i, log in enumerate(([], [LogLine(source="OCRAnnotator",
                                                              level="error", message="crash")])))
        store.put_scenes([fine, failed])
        documents = [store.scenes.find_one({"_id": s.id}) for s in (fine, failed)]
        store.scenes.delete_many({})
        followed = ObjectId()
        store.db.objects.insert_one({"_id": followed, "map": "site", "name": "followed",
                                     "state": "present"})
        for start in range(0, count, 10_000):
            scenes = [{**documents[i % 1000 == 999], "_id": ObjectId(),
                       "timestamp": STAMP + i * step}
                      for i in range(start, min(count, start + 10_000))]
            store.scenes.insert_many(scenes)
            store.db.events.insert_many([
                {"object_id": followed, "scene_id": s["_id"], "time": s["timestamp"],
                 "robot": "pr2", "map": "site", "explanation": "stay"} for s in scenes[::100]])
        client = TestClient(create_app(store, Settings(db=store.db.name, consolidator=False)),
                            base_url="http://127.0.0.1")
        middle = STAMP + count // 2 * step + 1
        api = {name: timed(client, "/api/playback?" + urlencode(
                   {"robot": "pr2", "map": "site", "t": middle, **query}), repeat)
               for name, query in {"at": {}, "next": {"step": "next"},
                                   "failure": {"step": "failure"},
                                   "event": {"step": "event", "object": followed}}.items()}
        page = timed(client, "/playback?" + urlencode(
            {"robot": "pr2", "map": "site", "t": middle, "object": followed}), repeat)
        return {"scenes": count, "api": api, "page_following_an_object": page}


def scene_pages(rng: np.random.Generator, image, big: Scene, repeat: int) -> dict:
    """Render times of the scene, cluster and scene log pages and of the images, over `big`
    and 200 more scenes."""
    others = [synthetic.scene(rng, STAMP + (i + 1) * 10**9, image=image) for i in range(200)]
    with scratch_store() as store:
        scenes = [big, *others]
        for start in range(0, len(scenes), BATCH):  # one transaction per batch
            store.put_scenes(scenes[start:start + BATCH])
        client = TestClient(create_app(store, Settings(db=store.db.name)),
                            base_url="http://127.0.0.1")
        result = {
            "scene_page_20_clusters": timed(client, f"/scenes/{big.id}", repeat),
            "cluster_page": timed(client, f"/clusters/{big.clusters[0].id}", repeat),
            "scene_log_page": timed(client, "/", repeat),
            "scene_log_filtered": timed(client, "/?" + urlencode(
                {"annotator": "OCRAnnotator", "type": "pm.annotation.Barcode"}), repeat),
            "crop_png": timed(client, f"/img/clusters/{big.clusters[0].id}/crop", repeat),
            "scene_thumbnail_png": timed(client, f"/img/scenes/{big.id}/thumb", repeat),
        }
        if "depth" in big.images:
            result["depth_png"] = timed(client, f"/img/scenes/{big.id}/images/depth", repeat)
        return result


def annotator_memory(store, count: int, progress: Progress) -> None:
    """`count` clusters in copies of the kitchen week's scenes (their logs and their
    clusters' annotations, crops and colour histograms left out), a scene a minute; each
    cluster also named by a detector (wrongly one time in ten), one in five with its ground
    truth. Documents are inserted prepared, in bulk, indexes built afterwards."""
    rng = np.random.default_rng(3)
    week = kitchen_week.generate(days=1)
    for scene in week.scenes:
        scene.ensure_id()
    written = documents.scene_documents(week.scenes, threshold=2**30)
    scenes = [bson.decode(raw.raw) for raw in written.scenes]
    clusters: dict = {}
    for raw in written.clusters:
        doc = bson.decode(raw.raw)
        doc.pop("hypotheses", None)
        doc.pop(documents.BLOBS_KEY, None)
        doc["annotations"] = [a for a in doc["annotations"]
                              if a["_type"] != "pm.annotation.ColorHistogram"]
        clusters[doc["_id"]] = doc
    truths = {scene.id: [kitchen_week.item_of(week.truth.object_at(i, j)).class_name
                         for j in range(len(scene.clusters))]
              for i, scene in enumerate(week.scenes)}
    classes = sorted({c for names in truths.values() for c in names})
    for collection in (SCENES, CLUSTERS):
        store.db[collection].drop_indexes()
    task = progress.add_task("annotator memory", total=count)
    done, i = 0, 0
    while done < count:
        batch_scenes, batch_clusters = [], []
        while len(batch_clusters) < 5000 and done + len(batch_clusters) < count:
            template = scenes[i % len(scenes)]
            stamp = STAMP + i * 60 * 10**9
            scene_id = ObjectId()
            copies = []
            for cluster_id, truth in zip(template["clusters"], truths[template["_id"]],
                                         strict=True):
                doc = clusters[cluster_id]
                named = truth if rng.random() > 0.1 else str(rng.choice(classes))
                extra = [{"_type": "pm.annotation.Detection", "_id": ObjectId(),
                          "source": "DeCafClassifier", "name": named}]
                if rng.random() < 0.2:
                    extra.append({"_type": "pm.annotation.GroundTruth", "_id": ObjectId(),
                                  "source": "", "class_name": truth})
                copies.append({**doc, "_id": ObjectId(), "scene_id": scene_id,
                               "annotations": doc["annotations"] + extra,
                               "search": {**doc["search"], "time": stamp}})
            batch_scenes.append({**template, "_id": scene_id, "timestamp": stamp,
                                 "clusters": [c["_id"] for c in copies]})
            batch_clusters += copies
            i += 1
        store.scenes.insert_many(batch_scenes, ordered=False)
        store.clusters.insert_many(batch_clusters, ordered=False)
        done += len(batch_clusters)
        progress.advance(task, len(batch_clusters))
    store.prepare()


def annotator_pages(count: int, repeat: int) -> dict:
    """Render times of the annotators page, a confusion cell's list and the JSON report over
    a memory of `count` clusters (annotator_memory)."""
    with scratch_store() as store:
        start = time.perf_counter()
        with Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
                      TimeElapsedColumn(), console=Console(stderr=True),
                      transient=True) as progress:
            annotator_memory(store, count, progress)
        built = time.perf_counter() - start
        client = TestClient(create_app(store, Settings(db=store.db.name, consolidator=False)),
                            base_url="http://127.0.0.1")
        first, last = (store.scenes.find_one(sort=[("timestamp", order)])["timestamp"]
                       for order in (1, -1))
        midway = {"scenes": 500, "before": (first + last) // 2}
        page = client.get("/annotators").text
        cell = html.unescape(re.search(r'<a href="(/annotators/clusters[^"]+)" data-count',
                                       page).group(1))
        report = client.get("/api/annotators").json()
        return {
            "clusters": store.clusters.estimated_document_count(),
            "scenes": store.scenes.estimated_document_count(), "build_s": round(built, 1),
            "window_500": {"hours": len({h["hour"] for h in report["hours"]}),
                           "comparisons": len(report["comparisons"]),
                           "classes_compared": max(len(c["scores"])
                                                   for c in report["comparisons"])},
            "page_500_scenes": timed(client, "/annotators", repeat),
            "page_5000_scenes": timed(client, "/annotators?scenes=5000", repeat),
            "page_500_midway": timed(client, "/annotators?" + urlencode(midway), repeat),
            "cell_list": timed(client, cell, repeat),
            "api_500_scenes": timed(client, "/api/annotators", repeat),
            "kb_500_scenes": round(len(page.encode()) / 1024, 1)}


FACET_VALUES = {"robot": [f"robot{i}" for i in range(3)],
                "regions": [f"region{i}" for i in range(12)],
                "annotators": [f"Annotator{i}" for i in range(12)],
                "types": [f"pm.annotation.Type{i}" for i in range(15)]}


def facets(count: int, repeat: int) -> dict:
    """The scene log with its facet counts (webui/facets.py) over `count` scenes (200,000 of 5
    clusters: a memory of 1,000,000 clusters), each with a robot of 3, 2 regions of 12, 6
    annotators of 12 and 8 types of 15: unfiltered, by one choice, by two, by a time range;
    the page's time, the counts' alone and the histogram's over time."""
    rng = np.random.default_rng(3)
    step = 365 * 86_400 * 10**9 // count
    with scratch_store() as store:
        for start in range(0, count, 10_000):
            store.scenes.insert_many([{
                "_id": ObjectId(), "_type": "pm.scene.Scene", "timestamp": STAMP + i * step,
                "time": datetime_from_timestamp(STAMP + i * step), "map": "site",
                "robot": FACET_VALUES["robot"][int(rng.integers(3))], "clusters": [],
                "summary": {"clusters": 5, "labels": [], **{
                    key: sorted(rng.choice(FACET_VALUES[key], n, replace=False).tolist())
                    for key, n in (("regions", 2), ("annotators", 6), ("types", 8))}}}
                for i in range(start, min(count, start + 10_000))])
        client = TestClient(create_app(store, Settings(db=store.db.name, consolidator=False)),
                            base_url="http://127.0.0.1")
        middle = datetime_from_timestamp(STAMP + count // 2 * step).strftime("%Y-%m-%dT%H:%M")
        queries = {"unfiltered": {}, "robot": {"robot": "robot1"},
                   "robot_and_region": {"robot": "robot1", "region": "region3"},
                   "annotator_and_type": {"annotator": "Annotator2",
                                          "type": "pm.annotation.Type7"},
                   "robot_since": {"robot": "robot1", "since": middle}}
        counts = {}
        choices = {name: sorted(store.scenes.distinct(key)) for name, key in CHOICES.items()}
        for name, query in queries.items():
            given = {key: query.get(key, "") for key in (*CHOICES, "since", "until")}
            matched = scene_filter(given, choices["type"])
            times, drawn = [], []
            for _ in range(repeat):
                start = time.perf_counter()
                counted = facet_counts(store.scenes, matched, choices, CHOICES)
                times.append((time.perf_counter() - start) * 1000)
                start = time.perf_counter()
                histogram = scene_histogram(store.scenes, matched)
                drawn.append((time.perf_counter() - start) * 1000)
            times.sort()
            drawn.sort()
            counts[name] = {"median_ms": round(statistics.median(times), 1),
                            "p95_ms": round(times[int(0.95 * (len(times) - 1))], 1),
                            "values_counted": sum(map(len, counted.values())),
                            "not_counted_in_time": sum(n is None for c in counted.values()
                                                       for n in c.values()),
                            "histogram_median_ms": round(statistics.median(drawn), 1),
                            "histogram_p95_ms": round(drawn[int(0.95 * (len(drawn) - 1))], 1),
                            "histogram_drawn": histogram is not None}
        pages = {name: timed(client, "/scenes?" + urlencode(query), repeat)
                 for name, query in queries.items()}
        return {"scenes": count, "facet_counts": counts, "scene_log_page": pages}


SECTIONS = ("pages", "map", "search", "solid", "playback", "annotators", "facets")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeat", type=int, default=30)
    parser.add_argument("--map-days", type=int, default=7)
    parser.add_argument("--search-clusters", type=int, default=1_000_000)
    parser.add_argument("--keep", metavar="DB", help="build the large memory into DB, keep it")
    parser.add_argument("--playback-scenes", type=int, default=1_000_000)
    parser.add_argument("--annotator-clusters", type=int, default=1_000_000)
    parser.add_argument("--facet-scenes", type=int, default=200_000)
    parser.add_argument("--only", action="append", choices=SECTIONS,
                        help="run this section only (repeatable; default: every section)")
    args = parser.parse_args()
    sections = set(args.only or SECTIONS)
    result: dict = {"benchmark": "webui"}
    rng, image = np.random.default_rng(0), kitchen_image()
    big = synthetic.scene(rng, STAMP, clusters=20, image=image)
    if image is not None:
        big.images["color"] = Image(data=image)
    if depth := next(KITCHEN.glob("depth_*.png"), None):
        big.images["depth"] = Image(data=cv2.imread(str(depth), cv2.IMREAD_UNCHANGED),
                                    encoding="mono16")
    if "pages" in sections:
        result.update(scene_pages(rng, image, big, args.repeat))
    if "map" in sections:
        result["map_page"] = map_page(args)
    if "search" in sections and args.search_clusters:
        result["search_page"] = search_pages(args, big)
    if "solid" in sections:
        result["solid_views"] = solid_views(args.repeat)
    if "playback" in sections:
        result["playback"] = playback(args.playback_scenes, args.repeat)
    if "annotators" in sections and args.annotator_clusters:
        result["annotators_page"] = annotator_pages(args.annotator_clusters, args.repeat)
    if "facets" in sections and args.facet_scenes:
        result["facets"] = facets(args.facet_scenes, args.repeat)
    print_json(result)


if __name__ == "__main__":
    main()
