"""Find more like this: descriptors as vectors, the vector index kept beside MongoDB, the
query over the API, the CLI and the page, on a generated kitchen day."""

from __future__ import annotations

import base64
import json
import os
import re
import sys
import threading
import time
from collections import Counter
from contextlib import contextmanager
from datetime import UTC, datetime, timedelta
from pathlib import Path

import cv2
import numpy as np
import pytest
from bson import ObjectId
from click.testing import CliRunner
from fastapi.testclient import TestClient
from playwright.sync_api import expect

from percept_memory.cli import main
from percept_memory.demo import kitchen_week
from percept_memory.ingest import backends
from percept_memory.memory import index_keeper, similarity
from percept_memory.memory.index_keeper import IndexKeeper
from percept_memory.memory.schema import CLUSTERS, OUTBOX, SCENES
from percept_memory.memory.settings import Settings
from percept_memory.memory.similarity import RowFilter, SimilarityIndex
from percept_memory.memory.types import ColorHistogram, FeatureVector, ImageROI
from percept_memory.memory.types.appearance import (
    crop_descriptors,
    orb_features,
    vocabulary,
)
from percept_memory.memory.types.orb_vocabulary import learn_vocabulary
from percept_memory.memory.types.visual_words import VisualWords
from percept_memory.queries.similar import Similarity
from percept_memory.webui.app import create_app

from .conftest import LOCAL, ingest_consolidated, served
from .test_webui import ALL_LOADED, browser, page, shot  # noqa: F401 (fixtures)

KITCHEN_FRAMES = sorted((Path(__file__).resolve().parents[2] / "shared/data/robosherlock/samples/"
                         "kitchen").glob("rgb_*.png"))


@pytest.fixture(scope="module")
def day(store):
    """A kitchen day, consolidated: the week and cluster id -> the catalogue item it shows."""
    week = kitchen_week.generate(days=1)
    ingest_consolidated(store, week.scenes)
    item = {cluster.id: kitchen_week.item_of(week.truth.object_at(i, j)).key
            for i, scene in enumerate(week.scenes) for j, cluster in enumerate(scene.clusters)}
    return week, item


@pytest.fixture(scope="module")
def settings(tmp_path_factory, mongo_uri, db_name) -> Settings:
    return Settings(mongodb_uri=mongo_uri, db=db_name,
                    data_dir=tmp_path_factory.mktemp("data"), consolidator=False)


# --- descriptors ------------------------------------------------------------------------------


def test_descriptors_rank_as_the_types_similarities():
    rng = np.random.default_rng(1)
    h = [ColorHistogram(histogram=rng.random((16, 16))) for _ in range(3)]
    f = [FeatureVector(name="VFH", vector=rng.normal(size=308)) for _ in range(3)]
    for items, kind in ((h, ColorHistogram), (f, FeatureVector)):
        (name,) = items[0].descriptors()
        vectors = np.stack([item.descriptors()[name] for item in items])
        assert np.allclose(np.clip(vectors @ vectors.T, 0, 1), kind.similarities(items, items))
    rois = [ImageROI(box=(0, 0, 8, 8), phash=p)
            for p in ("0123456789abcdef", "0123456789abcdee", "fedcba9876543210")]
    bits = np.stack([roi.descriptors()["phash"] for roi in rois])
    distances = [0, 1, sum(bin(a ^ b).count("1") for a, b in zip(
        bytes.fromhex(rois[0].phash), bytes.fromhex(rois[2].phash), strict=True))]
    assert np.allclose(bits @ bits[0], [1 - 2 * d / 64 for d in distances])
    assert FeatureVector(name="x", vector=np.zeros(4)).descriptors() == {}


def test_crops_of_the_same_item_look_more_alike_than_other_items():
    rng = np.random.default_rng(2)
    keys = ["corn_flakes", "cup", "ketchup", "apple", "milka"]
    described = {key: [crop_descriptors(*kitchen_week.crop(key, "front", rng)) for _ in range(2)]
                 for key in keys}
    printed = [key for key in keys if key != "apple"]  # a plain apple has no ORB keypoints
    for name, among in (("crop-colour", keys), ("crop-hog", keys), ("crop-orb", printed)):
        for key in among:
            same = described[key][0][name] @ described[key][1][name]
            others = [described[key][0][name] @ described[o][1][name] for o in among if o != key]
            assert same > max(others), (name, key)


def test_visual_words_are_the_crops_orb_features_on_the_shipped_vocabulary():
    rng = np.random.default_rng(3)
    pixels, mask = kitchen_week.crop("corn_flakes", "front", rng)
    words = VisualWords.of_crop(pixels, mask)
    assert words.counts.shape == (64,) and words.counts.sum() == len(orb_features(pixels, mask))
    assert np.allclose(words.descriptors()["crop-orb"], crop_descriptors(pixels, mask)["crop-orb"])
    assert VisualWords.of_crop(np.full((64, 64, 3), 128, np.uint8)) is None  # nothing to find
    for foreign in (np.arange(3), np.full(64, -1), np.full(64, 1j), np.full(64, np.nan)):
        assert not VisualWords(counts=foreign).descriptors()  # another vocabulary's, or none
    assert "crop-orb" not in crop_descriptors(np.full((64, 64, 3), 128, np.uint8))
    outside = np.zeros_like(mask)
    outside[:8, :8] = 255  # keypoints only where the mask is
    assert VisualWords.of_crop(pixels, outside) is None


@pytest.mark.skipif(not KITCHEN_FRAMES, reason="the RoboSherlock sample frame is not beside")
def test_the_shipped_vocabulary_is_what_its_documented_command_makes():
    products = sorted((Path(backends.__file__).parent / "products").glob("*.jpg"))
    learnt = learn_vocabulary([*KITCHEN_FRAMES, *products])
    assert learnt["words"].shape == (64, 32) and np.array_equal(learnt["words"], vocabulary())


# --- the index --------------------------------------------------------------------------------


def test_the_index_is_built_saved_loaded_and_caught_up(store, day, tmp_path, monkeypatch):
    monkeypatch.setattr(similarity, "CHUNK", 7)  # read in chunks: the vectors outgrow the rows
    clusters = store.db[CLUSTERS].count_documents({})
    index = SimilarityIndex(store, tmp_path / "index")
    assert index.refresh() == clusters
    assert (tmp_path / "index" / "rows.json").exists()
    assert set(index.names()) >= {"crop-colour", "crop-hog", "phash", "histogram-HS-256"}

    again = SimilarityIndex(store, tmp_path / "index")
    assert again.refresh() == 0  # loaded from its files, nothing to read from MongoDB
    some = next(iter(day[1]))
    assert all(np.array_equal(v, again.descriptors_of(some)[n])
               for n, v in index.descriptors_of(some).items())

    newer = kitchen_week.generate(days=1, seed=7).scenes[:2]
    stored = store.put_scenes(newer)
    ids = [c for s in stored for c in s.cluster_ids]
    assert again.refresh() == len(ids)
    assert again.descriptors_of(ids[0])

    removed = list(store.db[CLUSTERS].find({"_id": {"$in": ids}}))
    store.db[CLUSTERS].delete_many({"_id": {"$in": ids}})  # gone from the source of truth
    assert again.refresh() == len(ids)
    found = again.search(again.descriptors_of(some), 1000)
    assert len(found) == store.db[CLUSTERS].count_documents({})
    assert not {m.cluster_id for m in found} & set(ids)

    store.db[CLUSTERS].insert_many(removed)  # and back again
    assert again.refresh() == len(ids)
    assert again.refresh() == 0
    assert set(ids) <= {m.cluster_id for m in again.search(again.descriptors_of(some), 1000)}
    for collection in (SCENES, OUTBOX):  # the other tests know the day's scenes only
        store.db[collection].delete_many({"_id": {"$in": [s.scene_id for s in stored]}})
    store.db[CLUSTERS].delete_many({"_id": {"$in": ids}})


def test_the_index_reads_only_the_parts_that_give_descriptors_and_describes_alike(store, day):
    ids = list(day[1])[:40]
    whole, parts = store.get_clusters(ids), store.get_clusters(ids, similarity.described_kinds())
    assert parts.keys() == whole.keys() == set(ids)
    for cluster_id, cluster in whole.items():
        read = parts[cluster_id]
        assert len(read.annotations) < len(cluster.annotations)  # its location, names... left
        assert read.scene_id == cluster.scene_id
        described, expected = read.descriptors(), cluster.descriptors()
        assert described.keys() == expected.keys() and len(expected) >= 4
        assert all(np.array_equal(described[name], expected[name]) for name in expected)


def test_a_refresh_reads_only_the_ids_stored_since_the_last(store, day, tmp_path, monkeypatch):
    monkeypatch.setattr(similarity, "MARGIN", timedelta(0))  # no transaction is open
    newest = store.db[CLUSTERS].find_one(sort=[("_id", -1)])["_id"].generation_time
    while datetime.now(UTC).replace(microsecond=0) <= newest:  # ids tell whole seconds only:
        time.sleep(0.05)  # a read within the newest cluster's second must read that second again
    index = SimilarityIndex(store, tmp_path / "index")
    index.refresh()
    read = []
    monkeypatch.setattr(index, "_ids", lambda query: read.extend(
        SimilarityIndex._ids(index, query)) or read)
    index.refresh()
    assert read == []  # not the newest cluster again, nor any stored before the last read


def test_an_unreadable_or_older_index_is_rebuilt_from_mongodb(store, day, tmp_path):
    folder = tmp_path / "index"
    SimilarityIndex(store, folder).refresh()
    state = json.loads((folder / "rows.json").read_text())
    (folder / "rows.json").write_text(json.dumps({**state, "format": 0}))
    assert SimilarityIndex(store, folder).refresh() == store.db[CLUSTERS].count_documents({})
    for file in folder.glob("*.usearch"):
        file.write_bytes(b"not an index")
    assert SimilarityIndex(store, folder).refresh() == store.db[CLUSTERS].count_documents({})

    rows = (folder / "rows.npz").read_bytes()
    grown = SimilarityIndex(store, folder)
    grown.refresh()
    stored = store.put_scenes(kitchen_week.generate(days=1, seed=8).scenes[:1])
    grown.refresh()
    grown.save()
    (folder / "rows.npz").write_bytes(rows)  # as if the save had stopped before the rows
    assert SimilarityIndex(store, folder).refresh() == store.db[CLUSTERS].count_documents({})
    for collection, key in ((CLUSTERS, "scene_id"), (SCENES, "_id"), (OUTBOX, "_id")):
        store.db[collection].delete_many({key: stored[0].scene_id})


@pytest.mark.parametrize("layout_tail", [0, 1000, similarity.LAYOUT_TAIL])
def test_a_filter_passes_the_rows_it_should_as_rows_are_added_and_removed(monkeypatch,
                                                                          layout_tail):
    """The rows laid out again at every batch (0), at some (1000) or never (the default: the
    3,000 rows stay rows added since the layout)."""
    monkeypatch.setattr(similarity, "LAYOUT_TAIL", layout_tail)
    rng = np.random.default_rng(0)
    rows = similarity.Rows()
    times = rng.integers(0, 100, 3000)  # out of order, many alike: window ends are inclusive
    robots, regions, maps = rng.choice(["r", "s"], 3000), rng.choice(["a", "b"], 3000), \
        rng.choice(["m", "n", None], 3000)
    for first in range(0, len(times), 700):  # added in batches, filtered between them
        for row in range(first, min(first + 700, len(times))):
            rows.add(ObjectId(), int(times[row]),
                     {"robot": robots[row], "region": regions[row], "map": maps[row]})
        rows.remove(int(rng.integers(len(rows))))
        live = rows.columns["live"][:len(rows)]
        assert rows.live_count() == live.sum() < len(rows)
        for after, before in [(10, 20), (None, 50), (50, None), (30, 30), (None, None)]:
            for where in ({"region": ["a"]}, {"robot": ["s"], "map": ["m"]}):
                expected = [row for row in range(len(rows)) if live[row]
                            and all({"robot": robots, "region": regions, "map": maps}[key][row]
                                    in wanted for key, wanted in where.items())
                            and (after is None or times[row] >= after)
                            and (before is None or times[row] <= before)]
                found = rows.passing(RowFilter(**where, after=after, before=before))
                assert sorted(found.rows().tolist()) == expected


@pytest.mark.parametrize("exact_rows", [similarity.EXACT_ROWS, 0])
def test_filters_hold_whether_searched_exactly_or_approximately(store, day, tmp_path,
                                                                monkeypatch, exact_rows):
    monkeypatch.setattr(similarity, "EXACT_ROWS", exact_rows)
    index = SimilarityIndex(store, tmp_path / "index")
    index.refresh()
    start = next(iter(day[1]))
    query = index.descriptors_of(start)
    docs = {d["_id"]: d["search"] for d in store.db[CLUSTERS].find({}, {"search": 1})}
    times = sorted(s["time"] for s in docs.values())
    middle = times[len(times) // 3], times[2 * len(times) // 3]
    for where, holds in [
        (RowFilter(region=["table"]), lambda s: s["region"] == "table"),
        (RowFilter(after=middle[0], before=middle[1]),
         lambda s: middle[0] <= s["time"] <= middle[1]),
        (RowFilter(robot=["pr2"], map=[kitchen_week.MAP], region=["shelf", "table"]),
         lambda s: s["region"] in ("shelf", "table")),
    ]:
        found = index.search(query, 10, where, exclude=[start])
        passing = [i for i, s in docs.items() if holds(s) and i != start]
        assert len(found) == min(10, len(passing))
        assert all(holds(docs[m.cluster_id]) for m in found)
        assert [m.similarity for m in found] == sorted((m.similarity for m in found),
                                                       reverse=True)
    assert index.search(query, 10, RowFilter(map=["another-map"])) == []
    assert index.search(query, 10, RowFilter(robot=["nobody"])) == []


def keepers() -> set[threading.Thread]:
    return {t for t in threading.enumerate() if t.name == "pmem-similarity"}


def test_a_keeper_catches_up_in_a_thread_of_lower_priority(store, day, tmp_path):
    index = SimilarityIndex(store, tmp_path / "index")
    keeper = IndexKeeper(index, niceness=19)
    before = keepers()
    try:
        assert keeper.current(timeout=60) == 0
        assert index.rows.live_count() == store.db[CLUSTERS].count_documents({})
        if sys.platform == "linux":  # the thread's own niceness; the process keeps its own
            assert os.getpriority(os.PRIO_PROCESS, keeper.native_id) == 19
            assert os.getpriority(os.PRIO_PROCESS, threading.get_native_id()) < 19
    finally:
        keeper.stop()
    assert keepers() <= before


@contextmanager
def more_scenes(store):
    """Yields `put(scenes)`, which stores scenes for one test and returns their clusters' ids;
    they are deleted after it (the other tests know the day's scenes only)."""
    stored = []

    def put(scenes):
        new = store.put_scenes(scenes)
        stored.extend(new)
        return [c for s in new for c in s.cluster_ids]

    try:
        yield put
    finally:
        for collection in (SCENES, OUTBOX):
            store.db[collection].delete_many({"_id": {"$in": [s.scene_id for s in stored]}})
        store.db[CLUSTERS].delete_many({"_id": {"$in": [c for s in stored
                                                         for c in s.cluster_ids]}})


def test_the_files_are_written_in_proportion_and_when_the_keeper_stops(store, day, tmp_path,
                                                                      monkeypatch):
    monkeypatch.setattr(similarity, "SAVE_EVERY", 1)  # the share decides
    index = SimilarityIndex(store, tmp_path / "index")
    keeper = IndexKeeper(index, niceness=19)
    with more_scenes(store) as put:
        ids = put(kitchen_week.generate(days=1, seed=7).scenes[:2])
        try:
            assert keeper.current(timeout=60) == 0
            assert index.unsaved == 0  # the first catch-up is written at once
            newer = put(kitchen_week.generate(days=1, seed=8).scenes[:2])
            ids += newer
            assert keeper.current(timeout=60) == 0
            assert len(newer) < len(index.rows) // similarity.SAVE_SHARE
            assert index.unsaved == len(newer)  # fewer than an eighth of the rows: not written
            keeper.stop()
            again = SimilarityIndex(store, tmp_path / "index")
            again.load()
            assert all(again.rows.holds(i) for i in ids)  # written as the keeper stopped
        finally:
            keeper.stop()


@pytest.mark.parametrize("max_defer_s", [60.0, 0.2])
def test_a_keeper_waits_while_clusters_are_stored_in_bulk(store, day, tmp_path, monkeypatch,
                                                          max_defer_s):
    """Storing that goes on (here any: the thresholds lowered) is not slowed by describing
    it: the keeper waits for a pause, then catches up; at most max_defer_s at a time."""
    monkeypatch.setattr(index_keeper, "BURST", 1)
    monkeypatch.setattr(index_keeper, "BURST_PER_S", 1.0)
    monkeypatch.setattr(index_keeper, "PROBE_S", 0.05)
    monkeypatch.setattr(index_keeper, "MAX_DEFER_S", max_defer_s)
    index = SimilarityIndex(store, tmp_path / "index")
    keeper = IndexKeeper(index, niceness=19, poll_s=0.25)  # longer than between two scenes
    scenes = kitchen_week.generate(days=1, seed=9).scenes[:30]
    with more_scenes(store) as put:
        try:
            assert keeper.current(timeout=60) == 0  # nothing being stored: caught up
            held = index.rows.live_count()
            storing = threading.Thread(target=lambda: [(put([s]), time.sleep(0.02))
                                                       for s in scenes])
            storing.start()
            time.sleep(0.3)
            behind = keeper.current(timeout=0.3)
            storing.join()
            grew = index.rows.live_count() - held  # described while it was stored
            if max_defer_s > 1:
                assert behind > 0 and grew == 0
            else:  # a bulk load that does not pause is described every max_defer_s
                assert grew > 0
            assert keeper.current(timeout=60) == 0  # the pause: caught up
            assert index.rows.live_count() == store.db[CLUSTERS].count_documents({})
        finally:
            keeper.stop()


def test_a_keeper_that_fails_to_catch_up_keeps_trying(store, day, tmp_path, monkeypatch, caplog):
    index = SimilarityIndex(store, tmp_path / "index")
    refresh, failures = index.refresh, []

    def fails_once():
        if not failures:
            failures.append(1)
            raise RuntimeError("a cluster that does not decode")
        return refresh()

    monkeypatch.setattr(index, "refresh", fails_once)
    keeper = IndexKeeper(index, niceness=19, poll_s=0.05)
    try:
        assert keeper.current(timeout=0.01) > 0  # the first catch-up failed
        assert keeper.current(timeout=60) == 0
    finally:
        keeper.stop()
    assert "could not catch up" in caplog.text and "does not decode" in caplog.text


def test_a_search_answers_while_the_keeper_is_still_describing(store, day, settings, tmp_path,
                                                              monkeypatch):
    """A burst of ingest the keeper has not described yet: the search waits for it at most
    similarity_wait_s, then searches what is indexed, says how many it could not, and can
    start from a cluster not indexed yet; the index is not held while clusters are described."""
    index = SimilarityIndex(store, tmp_path / "index")
    ids = store.db[CLUSTERS].distinct("_id")
    index.add(index.described(ids[: len(ids) // 2]))  # the rest is the burst
    release = threading.Event()
    describe = index.described

    def held_back(cluster_ids):
        if threading.current_thread().name == "pmem-similarity":
            release.wait(60)
        return describe(cluster_ids)

    monkeypatch.setattr(index, "described", held_back)
    search = Similarity(store, settings.model_copy(update={"similarity_wait_s": 0.3}), index,
                        in_background=True)
    try:
        start = time.monotonic()
        page = search.similar_to(cluster=ids[-1], k=5)  # a cluster of the burst
        assert time.monotonic() - start < 5
        assert page.not_indexed_yet == len(ids) - len(ids) // 2
        assert len(page.items) == 5 and {h.id for h in page.items} <= set(ids[: len(ids) // 2])
        release.set()
        page = search.similar_to(cluster=ids[-1], k=5)
        assert page.not_indexed_yet == 0
        assert index.rows.live_count() == len(ids)
    finally:
        release.set()
        search.close()


def test_the_same_item_comes_first(store, day, settings):
    """Precision at 5 of "same item" from every cluster of the day (the bench measures it
    over the week per descriptor: bench/similarity.py)."""
    item = day[1]
    similar = Similarity(store, settings)
    hits = [similar.similar_to(cluster=c, k=5).items for c in list(item)[::3]]
    precision = np.mean([np.mean([item[h.id] == item[c] for h in found])
                         for c, found in zip(list(item)[::3], hits, strict=True)])
    assert precision > 0.8


# --- API, CLI, page ----------------------------------------------------------------------------


@pytest.fixture(scope="module")
def client(store, day, settings):
    return TestClient(create_app(store, settings), base_url=LOCAL)


def _png(pixels: np.ndarray) -> str:
    return base64.b64encode(cv2.imencode(".png", pixels)[1].tobytes()).decode()


def test_the_api_finds_more_like_a_cluster_an_object_and_an_image(client, store, day):
    item = day[1]
    start = next(c for c, key in item.items() if key == "corn_flakes")
    answer = client.get("/api/similar", params={"cluster": str(start), "k": 4,
                                                "region": "shelf"})
    assert answer.status_code == 200, answer.text
    body = answer.json()
    assert body["start"] == str(start) and "crop-colour" in body["descriptors"]
    assert body["not_indexed_yet"] == 0
    assert len(body["items"]) == 4 and all(h["region"] == "shelf" for h in body["items"])
    assert all(item[ObjectId(h["id"])] == "corn_flakes" for h in body["items"])
    assert body["items"][0]["similarity"] >= body["items"][-1]["similarity"]

    cluster = store.get_cluster(start)
    by_object = client.get("/api/similar", params={"object": str(cluster.object_id)})
    assert by_object.status_code == 200 and by_object.json()["items"]
    by_name = client.get("/api/similar", params={"object": "ketchup", "k": 3}).json()
    assert item[ObjectId(by_name["start"])] == "ketchup"
    assert [item[ObjectId(h["id"])] for h in by_name["items"]] == ["ketchup"] * 3

    pixels, _ = kitchen_week.crop("ketchup", "front", np.random.default_rng(5))
    uploaded = client.post("/api/similar", json={"image": _png(pixels), "k": 3})
    assert uploaded.status_code == 200, uploaded.text
    found = uploaded.json()["items"]
    assert [item[ObjectId(h["id"])] for h in found] == ["ketchup"] * 3


@pytest.mark.parametrize(("method", "request_args", "status", "words"), [
    ("get", {"params": {"cluster": "65e5a0c0e4b0a1b2c3d4e5f6"}}, 404, "cluster"),
    ("get", {"params": {"object": "65e5a0c0e4b0a1b2c3d4e5f6"}}, 404, "object"),
    ("get", {"params": {"object": "unicorn"}}, 404, "unicorn"),
    ("get", {"params": {}}, 422, "one of cluster, object or image"),
    ("get", {"params": {"cluster": "nope"}}, 422, "not valid"),
    ("get", {"params": {"cluster": "65e5a0c0e4b0a1b2c3d4e5f6", "k": "0"}}, 422, "not valid"),
    ("get", {"params": {"image": "aGVsbG8="}}, 422, "JSON body"),
    ("post", {"json": {"image": "not base64!"}}, 422, "not base64"),
    ("post", {"json": {"image": "aGVsbG8="}}, 422, "not a PNG or JPEG"),
    ("post", {"json": {"image": "A" * (6 * 2**20)}}, 413, "at most"),
    ("post", {"content": b"image=1", "headers": {"content-type": "text/plain"}}, 415,
     "application/json"),
])
def test_bad_requests_get_the_json_error_shape(client, method, request_args, status, words):
    answer = getattr(client, method)("/api/similar", **request_args)
    assert answer.status_code == status, answer.text
    error = answer.json()["error"]
    assert error["status"] == status
    assert words in error["message"] + json.dumps(error["problems"])


def test_an_image_too_large_is_refused_from_its_header(client):
    huge = cv2.imencode(".png", np.zeros((2100, 2100), np.uint8))[1].tobytes()
    answer = client.post("/api/similar", json={"image": base64.b64encode(huge).decode()})
    assert answer.status_code == 422 and "over the limit" in answer.json()["error"]["message"]


def test_search_results_lead_to_more_like_each(client, day):
    found = client.get("/search", params={"text": "ketchup"})
    assert found.status_code == 200
    linked = re.findall(r'href="/similar\?cluster=([0-9a-f]{24})"', found.text)
    assert linked and linked == re.findall(r'data-cluster="([0-9a-f]{24})"', found.text)
    assert client.get(f"/similar?cluster={linked[0]}").status_code == 200


def test_a_filter_on_an_unknown_descriptor_names_those_there_are(client, day):
    answer = client.get("/api/similar", params={"cluster": str(next(iter(day[1]))),
                                                "descriptor": "colour"})
    assert answer.status_code == 422
    assert "crop-colour" in answer.json()["error"]["message"]


def test_the_page_says_what_it_could_not_search_yet_and_the_app_stops_its_keeper(
        store, day, settings, tmp_path, monkeypatch):
    release = threading.Event()
    describe = SimilarityIndex.described

    def held_back(self, cluster_ids):
        if threading.current_thread().name == "pmem-similarity":
            release.wait(60)
        return describe(self, cluster_ids)

    monkeypatch.setattr(SimilarityIndex, "described", held_back)
    before = keepers()
    app = create_app(store, settings.model_copy(update={"similarity_wait_s": 0.2,
                                                        "data_dir": tmp_path}))
    with TestClient(app, base_url=LOCAL) as client:
        answer = client.get("/similar", params={"cluster": str(next(iter(day[1])))})
        release.set()
    assert answer.status_code == 200
    clusters = store.db[CLUSTERS].count_documents({})
    assert f"{clusters} observations were stored too recently to be searched" in answer.text
    assert keepers() <= before  # the app's keeper ended with it


def test_pmem_query_similar(settings, day, mongo_uri, db_name, tmp_path):
    start = next(iter(day[1]))
    env = {"MONGODB_URI": mongo_uri, "PMEM_DB": db_name, "PMEM_DATA_DIR": str(settings.data_dir)}
    result = CliRunner().invoke(main, ["query", "similar", "--cluster", str(start), "--k", "3",
                                       "--json"], env=env)
    assert result.exit_code == 0, result.output
    items = json.loads(result.stdout)["items"]
    assert len(items) == 3 and all(day[1][ObjectId(h["id"])] == day[1][start]
                                   for h in items)

    crop = tmp_path / "crop.png"
    cv2.imwrite(str(crop), kitchen_week.crop("corn_flakes", "front", np.random.default_rng(3))[0])
    text = CliRunner().invoke(main, ["query", "similar", "--image", str(crop), "--k", "2"],
                              env=env)
    assert text.exit_code == 0, text.output
    assert "similarity" in text.stdout and "cereal" in text.stdout

    nothing = CliRunner().invoke(main, ["query", "similar", "--cluster", str(start),
                                        "--map", "elsewhere"], env=env)
    assert nothing.exit_code == 1 and nothing.stderr.startswith("Error: nothing else")
    bad = CliRunner().invoke(main, ["query", "similar"], env=env)
    assert bad.exit_code == 1 and "one of cluster, object or image" in bad.stderr


@pytest.fixture(scope="module")
def url(store, day, settings):
    """A real uvicorn server on a free loopback port, in a thread."""
    with served(create_app(store, settings)) as url:
        yield url


def test_more_like_this_shows_ranked_crops(page, url, day):  # noqa: F811 (page: a fixture)
    """From a cluster's page, "more like this" lists crops best first with their similarity;
    each leads on to more like it."""
    item = day[1]
    (often, _), = Counter(item.values()).most_common(1)
    start = next(c for c, key in item.items() if key == often)
    page.goto(f"{url}/clusters/{start}")
    page.get_by_role("link", name="more like this").click()
    expect(page).to_have_url(f"{url}/similar?cluster={start}")
    hits = page.locator("ol.similar li.hit")
    expect(hits).to_have_count(10)
    deadline = time.monotonic() + 10  # every crop decodes (lazy ones load after `load`)
    while not page.evaluate(ALL_LOADED):
        assert time.monotonic() < deadline, "a crop did not decode"
        page.wait_for_timeout(50)
    shown = [float(s) for s in hits.locator(".similarity").all_inner_texts()]
    assert shown == sorted(shown, reverse=True) and shown[0] > 0.5
    found = [ObjectId(i) for i in hits.evaluate_all("els => els.map(e => e.dataset.cluster)")]
    assert all(item[i] == often for i in found[:3])
    shot(page, "similar")
    hits.nth(1).get_by_role("link", name="more like this").click()
    expect(page).to_have_url(re.compile(rf"/similar\?cluster={found[1]}"))
    expect(page.locator("ol.similar li.hit")).to_have_count(10)

    page.goto(f"{url}/similar?cluster={start}&k=500")
    expect(page.locator("main")).to_contain_text("less than or equal to 100")


def _found_items(tab, item) -> list[str]:
    """The items shown on a /similar page, best first."""
    hits = tab.locator("ol.similar li.hit")
    expect(hits).to_have_count(10)
    return [item[ObjectId(i)] for i in hits.evaluate_all("els => els.map(e => e.dataset.cluster)")]


def test_more_like_this_from_the_scene_and_object_pages(page, url, store, day):  # noqa: F811 (page)
    """Every cluster of a scene page, an object page (from its latest observation) and each
    crop of its history lead to the crops that look like them."""
    item = day[1]
    scene = store.db[SCENES].find_one({"clusters.2": {"$exists": True}})
    cluster_id = scene["clusters"][2]
    page.goto(f"{url}/scenes/{scene['_id']}")
    page.locator("article.cluster").nth(2).get_by_role("link", name="more like this").click()
    expect(page).to_have_url(f"{url}/similar?cluster={cluster_id}")
    assert _found_items(page, item)[:3] == [item[cluster_id]] * 3

    object_id = store.get_cluster(cluster_id).object_id
    latest = store.db["objects"].find_one({"_id": object_id})["last_cluster"]
    page.goto(f"{url}/objects/{object_id}")
    page.locator(".overview > a.more-like-this").click()
    expect(page).to_have_url(f"{url}/similar?object={object_id}")
    expect(page.locator(".similar-start a").first).to_have_attribute("href",
                                                                      f"/clusters/{latest}")
    assert _found_items(page, item)[:3] == [item[cluster_id]] * 3

    page.go_back()
    oldest = page.locator("ol.crops li").last
    shown = oldest.locator("a").first.get_attribute("href").removeprefix("/clusters/")
    oldest.get_by_role("link", name="more like this").click()
    expect(page).to_have_url(f"{url}/similar?cluster={shown}")
    assert _found_items(page, item)[0] == item[ObjectId(shown)]
