"""Enrichment workers against the real mongod: the durable queue, the pHash cache on real
images, the three backends, and a worker killed mid-lookup."""

from __future__ import annotations

import asyncio
import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections import Counter
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import cv2
import numpy as np
import pytest
from bson import ObjectId
from pymongo import AsyncMongoClient

from percept_memory.demo import kitchen_week
from percept_memory.ingest import rgbd
from percept_memory.ingest.backends import Finding
from percept_memory.ingest.backends.catalogue import SHIPPED, ProductCatalogue
from percept_memory.ingest.backends.simulated import (
    CATEGORY_MIX,
    PRODUCTS,
    SimulatedService,
    answer,
    sample_latency_s,
)
from percept_memory.ingest.jobs import JobQueue, LookupEnqueuer, job_report, utc_now
from percept_memory.ingest.lookup_cache import HashIndex, LookupCache
from percept_memory.ingest.lookups import Lookup
from percept_memory.ingest.phash import crop_phash, hamming
from percept_memory.ingest.service import IngestService
from percept_memory.ingest.workers import run_worker
from percept_memory.memory.async_store import AsyncMemoryStore
from percept_memory.memory.schema import (
    CALIBRATION,
    CATALOGUE,
    CATALOGUE_HISTORY,
    CATALOGUE_TRACKS,
    CLUSTERS,
    EVENTS,
    JOBS,
    LOOKUP_CACHE,
    MAPS,
    OBJECTS,
    OUTBOX,
    SCENES,
)
from percept_memory.memory.search_keys import normal_label
from percept_memory.memory.settings import Settings
from percept_memory.memory.store import CLIENT_OPTIONS
from percept_memory.memory.types import (
    Barcode,
    Cluster,
    Image,
    ImageROI,
    Logo,
    Product,
    Scene,
    Text,
    WebLookup,
)

from .conftest import LOCAL, ROBOSHERLOCK

KITCHEN = next((ROBOSHERLOCK / "samples" / "kitchen").glob("rgb_*.png"))
MUESLI_BOX = (298, 96, 80, 100)  # x, y, w, h in the kitchen frame
JUICE_CARTON = (242, 70, 53, 118)
DERIVED = {"text": Text, "logo": Logo, "product": Product, "barcode": Barcode}


@pytest.fixture
def fresh(store):
    """The module's store with no scenes, jobs or cached lookups left by other tests."""
    for name in (SCENES, CLUSTERS, JOBS, LOOKUP_CACHE, OUTBOX, MAPS, OBJECTS, EVENTS,
                 CALIBRATION, CATALOGUE, CATALOGUE_TRACKS, CATALOGUE_HISTORY):
        store.db[name].delete_many({})
    return store


def settings_for(mongo_uri: str, db_name: str, **overrides) -> Settings:
    return Settings(MONGODB_URI=mongo_uri, db=db_name, job_backoff_s=0.0, **overrides)


def ingest(store, scenes) -> None:
    IngestService(store).ingest_batch(scenes, wait=60)


async def until_idle(settings: Settings, **worker_options) -> Counter:
    """Run a worker until no job is queued or running, then stop it gracefully."""
    stop = asyncio.Event()
    worker = asyncio.create_task(run_worker(settings, stop=stop, **worker_options))
    client = AsyncMongoClient(settings.mongodb_uri)
    jobs = client[settings.db][JOBS]
    try:
        while not worker.done():
            await asyncio.sleep(0.1)
            if not await jobs.count_documents({"state": {"$in": ["queued", "running"]}}):
                break
        stop.set()
        return await worker
    finally:
        await client.close()


def scene_with_crops(crops: list[np.ndarray], timestamp: int) -> Scene:
    return Scene(timestamp=timestamp, robot="test", clusters=[
        Cluster(hypotheses=[ImageROI(box=(10, 20, crop.shape[1], crop.shape[0]),
                                     crop=Image(data=crop, encoding="bgr8"))])
        for crop in crops])


def kitchen_frame() -> np.ndarray:
    return cv2.imread(str(KITCHEN), cv2.IMREAD_COLOR)


def cut(image: np.ndarray, box: tuple[int, int, int, int]) -> np.ndarray:
    x, y, w, h = box
    return image[y : y + h, x : x + w].copy()


def jpeg(image: np.ndarray, quality: int) -> np.ndarray:
    return cv2.imdecode(cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, quality])[1], 1)


def same_object_again(frame: np.ndarray, box: tuple[int, int, int, int]) -> list[np.ndarray]:
    """The object re-cut as a later observation would: shifted a few pixels, scaled, JPEG."""
    x, y, w, h = box
    return [cut(frame, (x + 2, y - 1, w, h)),
            cv2.resize(cut(frame, box), None, fx=0.6, fy=0.6, interpolation=cv2.INTER_AREA),
            jpeg(cut(frame, box), 70),
            jpeg(cv2.resize(cut(frame, (x - 1, y + 1, w, h)), None, fx=1.5, fy=1.5), 80)]


# --- the queue ------------------------------------------------------------------------------------


def test_ingest_enqueues_one_job_per_cluster_with_a_crop(fresh):
    week = kitchen_week.generate(days=1)
    scenes = week.scenes[:4]
    ingest(fresh, scenes)
    clusters = sum(len(s.clusters) for s in scenes)
    assert fresh.db[JOBS].count_documents({"state": "queued", "kind": "lookup"}) == clusters
    ingest(fresh, scenes)  # stored before: nothing new to look up
    LookupEnqueuer(fresh).apply([s.id for s in scenes], "", None)  # again: harmless
    assert fresh.db[JOBS].count_documents({}) == clusters
    no_crop = Scene(timestamp=5, robot="test",
                    clusters=[Cluster(hypotheses=[ImageROI(box=(0, 0, 4, 4))])])
    ingest(fresh, [no_crop])
    assert fresh.db[JOBS].count_documents({}) == clusters
    # a crop whose lookup's results came with it (a scene log of an enriched memory): not
    # looked up again (it was, and each such cluster got its results twice)
    looked_up = scene_with_crops([cut(kitchen_frame(), MUESLI_BOX)], 6)
    looked_up.clusters[0].annotations.append(WebLookup(category="product", title="Müsli"))
    ingest(fresh, [looked_up])
    assert fresh.db[JOBS].count_documents({}) == clusters


def test_worker_appends_lookups_with_provenance_once(fresh, mongo_uri, db_name):
    scenes = kitchen_week.generate(days=1).scenes[:3]
    ingest(fresh, scenes)
    counts = asyncio.run(until_idle(settings_for(mongo_uri, db_name), backend="simulated"))
    cluster_ids = [c.id for s in scenes for c in s.clusters]
    assert counts["done"] == len(cluster_ids) and not counts["failed"]
    report = job_report(fresh, limit=100)
    assert report["counts"]["done"] == len(cluster_ids)
    for job in report["jobs"]:
        assert job["outcome"]["backend"] == "simulated" and job["outcome"]["annotations"] >= 1
    for cluster in fresh.get_clusters(cluster_ids).values():
        lookups = cluster.annotations_of(WebLookup)
        assert lookups, "every cluster got an answer"
        for found in lookups:
            assert found.provenance.backend == "simulated" and found.provenance.job_id
            if found.provenance.cached:
                assert found.provenance.hash_distance <= Settings().lookup_cache_radius
            else:
                assert 504 <= found.provenance.latency_ms <= 2314 + 100
            if found.category in DERIVED:
                assert any(a.source == found.source for a in cluster.annotations_of(
                    DERIVED[found.category]))
    # The same job run again (retried, or taken over after its worker died having appended):
    # nothing is added.
    before = {c.id: len(c.annotations) for c in fresh.get_clusters(cluster_ids).values()}
    job = fresh.db[JOBS].find_one({"cluster_id": cluster_ids[0]})
    asyncio.run(run_job_again(mongo_uri, db_name, job))
    after = {c.id: len(c.annotations) for c in fresh.get_clusters(cluster_ids).values()}
    assert after == before


async def run_job_again(mongo_uri: str, db_name: str, doc: dict) -> None:
    from percept_memory.ingest.jobs import Job

    store = AsyncMemoryStore(AsyncMongoClient(mongo_uri, **CLIENT_OPTIONS), db_name,
                             gridfs_threshold=Settings().gridfs_threshold)
    try:
        async with LookupCache(store.db[LOOKUP_CACHE], radius=10) as cache:
            lookup = Lookup(store, cache, SimulatedService(), timeout_s=10)
            outcome = await lookup.run(Job(doc["_id"], doc["cluster_id"], doc["_id"], 2))
        assert outcome["cached"] and outcome["hash_distance"] == 0
    finally:
        await store.close()


def test_lookups_do_not_rename_the_objects_they_are_wrong_about(fresh, mongo_uri, db_name):
    """The simulated service names any crop after one of the thesis' products (table 5.4):
    heard, but weak evidence, the kitchen's objects keep the names their own annotators gave."""
    ingest(fresh, kitchen_week.generate(days=1).scenes[:30])
    counts = asyncio.run(until_idle(settings_for(mongo_uri, db_name), backend="simulated",
                                    concurrency=32))
    assert counts["done"] > 50 and not counts["failed"]
    kitchen = {normal_label(n) for i in kitchen_week.CATALOGUE.values() for n in (i.name, i.brand)
               if n}
    wrong = {normal_label(n) for p in PRODUCTS for n in (p.name, p.brand)} - kitchen
    objects = list(fresh.db[OBJECTS].find())
    assert any(wrong & set(o["label_weights"]) for o in objects)
    assert not wrong & {o["name"] for o in objects}


# --- a loopback lookup service ------------------------------------------------------------------


class LookupServer:
    """A JSON lookup service on 127.0.0.1 whose behaviour a test scripts: `answers` is a list
    of (status, body or None, delay_s) used in turn (the last one repeats); a body given as
    bytes is sent as they are, with no length."""

    def __init__(self, answers: list[tuple[int, dict | None, float]], token: str | None = None):
        self.answers, self.token, self.requests = answers, token, []
        self.release = threading.Event()  # a delay of inf waits for this
        server = self

        class Handler(BaseHTTPRequestHandler):
            def do_POST(self):  # noqa: N802 - http.server's name
                body = json.loads(self.rfile.read(int(self.headers["content-length"])))
                server.requests.append({"auth": self.headers.get("authorization"), **body})
                status, payload, delay = server.answers[min(len(server.requests),
                                                            len(server.answers)) - 1]
                if server.token and self.headers.get("authorization") != f"Bearer {server.token}":
                    status, payload, delay = 401, {"error": "who are you"}, 0
                if delay == float("inf"):
                    server.release.wait(60)
                else:
                    time.sleep(delay)
                streamed = isinstance(payload, bytes)  # sent with no length, up to the close
                data = payload if streamed else json.dumps(payload or {}).encode()
                try:
                    self.send_response(status)
                    self.send_header("content-type", "application/json")
                    if not streamed:
                        self.send_header("content-length", str(len(data)))
                    self.end_headers()
                    self.wfile.write(data)
                except BrokenPipeError:  # the client gave up waiting
                    pass

            def log_message(self, *args):
                pass

        self.httpd = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self.httpd.server_address[1]}/lookup"
        threading.Thread(target=self.httpd.serve_forever, daemon=True).start()

    def close(self):
        self.release.set()
        self.httpd.shutdown()
        self.httpd.server_close()


ANSWER = {"results": [
    {"category": "product", "title": "Kölln Müsli", "brand": "Kölln", "box": [4, 4, 40, 50],
     "links": ["https://shop.invalid/koelln"], "properties": {"perishable": False}},
    {"category": "text", "title": "Knusper Honig-Nuss"},
    {"category": "barcode", "title": "4000540000108"},
]}


def test_http_backend_sends_the_crop_and_auth_and_appends_typed_results(fresh, mongo_uri,
                                                                          db_name):
    server = LookupServer([(200, ANSWER, 0)], token="s3cret")
    try:
        ingest(fresh, [scene_with_crops([cut(kitchen_frame(), MUESLI_BOX)], 1)])
        settings = settings_for(mongo_uri, db_name, lookup_url=server.url,
                                lookup_auth="Bearer s3cret")
        counts = asyncio.run(until_idle(settings, backend="http"))
    finally:
        server.close()
    assert counts["done"] == 1
    request = server.requests[0]
    assert request["auth"] == "Bearer s3cret" and (request["width"], request["height"]) == (80, 100)
    (cluster,) = fresh.get_clusters([fresh.db[CLUSTERS].find_one()["_id"]]).values()
    product = cluster.annotations_of(Product)[0]
    assert (product.name, product.brand, product.properties) == ("Kölln Müsli", "Kölln",
                                                                  {"perishable": False})
    assert cluster.annotations_of(Text)[0].text == "Knusper Honig-Nuss"
    assert cluster.annotations_of(Barcode)[0].symbology == "EAN-13"
    web = cluster.annotations_of(WebLookup)
    assert [w.category for w in web] == ["product", "text", "barcode"]
    assert web[0].box == (14, 24, 40, 50)  # crop pixels moved to the scene image
    assert fresh.db[CLUSTERS].find_one()["search"]["labels"].count("kölln") == 1


@pytest.mark.parametrize("answers, retried, error, requests", [
    ([(503, {"error": "overloaded"}, 0)], True, "HTTP 503 from", 6),  # + a quick retry each
    ([(200, ANSWER, 3.0)], True, "gave no answer within 0.5 s", 3),
    ([(200, {"results": [{"category": "spaceship", "title": "x"}]}, 0)], True, "not valid", 3),
    ([(400, {"error": "not an image"}, 0)], False, "HTTP 400 from", 1),
    # an answer too big to be findings, declared or streamed: read no further, not retried
    ([(200, {"results": [{"category": "text", "title": "x" * 5_000_000}]}, 0)], False,
     "bytes, more than 4,194,304", 1),
    ([(200, b'{"results": [{"category": "text", "title": "' + b"x" * 5_000_000, 0)], False,
     "is more than 4,194,304 bytes", 1),
])
def test_backend_failures_are_retried_then_fail_keeping_the_error(fresh, mongo_uri, db_name,
                                                                   answers, retried, error,
                                                                   requests):
    server = LookupServer(answers)
    try:
        ingest(fresh, [scene_with_crops([cut(kitchen_frame(), MUESLI_BOX)], 1)])
        settings = settings_for(mongo_uri, db_name, lookup_url=server.url, job_max_attempts=3,
                                lookup_retries=1, lookup_timeout_s=0.5)
        counts = asyncio.run(until_idle(settings, backend="http"))
    finally:
        server.close()
    job = fresh.db[JOBS].find_one()
    assert job["state"] == "failed" and error in job["error"]
    assert job["attempts"] == (3 if retried else 1)
    assert counts["failed"] == 1 and counts["retried"] == (2 if retried else 0)
    assert "due" not in job and "lease" not in job
    assert not fresh.db[CLUSTERS].find_one()["annotations"]
    assert len(server.requests) == requests


def test_a_job_done_on_a_later_attempt_shows_no_error(fresh, mongo_uri, db_name):
    """Done after a failed attempt, it still showed that attempt's error beside its outcome
    (pmem jobs, GET /api/jobs): a done job reads as a failure."""
    server = LookupServer([(503, {"error": "overloaded"}, 0)] * 2 + [(200, ANSWER, 0)])
    try:
        ingest(fresh, [scene_with_crops([cut(kitchen_frame(), MUESLI_BOX)], 1)])
        settings = settings_for(mongo_uri, db_name, lookup_url=server.url, job_max_attempts=3,
                                lookup_retries=1)
        counts = asyncio.run(until_idle(settings, backend="http"))
    finally:
        server.close()
    job = fresh.db[JOBS].find_one()
    assert (job["state"], job["attempts"], job["error"]) == ("done", 2, None)
    assert counts["retried"] == 1 and counts["done"] == 1


# --- crash and take-over --------------------------------------------------------------------------


def test_worker_killed_mid_lookup_job_done_once_by_another(fresh, mongo_uri, db_name):
    server = LookupServer([(200, ANSWER, float("inf")), (200, ANSWER, 0)])
    env = {**os.environ, "MONGODB_URI": mongo_uri, "PMEM_DB": db_name,
           "PMEM_LOOKUP_BACKEND": "http", "PMEM_LOOKUP_URL": server.url,
           "PMEM_JOB_LEASE_S": "1", "PMEM_LOOKUP_TIMEOUT_S": "60",
           "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    command = [sys.executable, "-m", "percept_memory", "worker"]
    first = second = None
    try:
        ingest(fresh, [scene_with_crops([cut(kitchen_frame(), MUESLI_BOX)], 1)])
        first = subprocess.Popen(command, env=env, stderr=subprocess.PIPE)
        deadline = time.monotonic() + 60
        while not server.requests:  # the first worker is now waiting on the service
            assert time.monotonic() < deadline and first.poll() is None
            time.sleep(0.05)
        lost = fresh.db[JOBS].find_one()["worker"]
        first.send_signal(signal.SIGKILL)
        first.wait()
        second = subprocess.Popen(command, env=env, stderr=subprocess.PIPE, text=True)
        while fresh.db[JOBS].find_one()["state"] != "done":
            assert time.monotonic() < deadline and second.poll() is None
            time.sleep(0.1)
        second.send_signal(signal.SIGTERM)  # graceful: exits 0 with a summary
        assert second.wait(60) == 0
        assert "1 jobs done" in second.stderr.read()
    finally:
        server.close()
        for process in (first, second):
            if process is not None and process.poll() is None:
                process.kill()
    job = fresh.db[JOBS].find_one()
    assert job["attempts"] == 2 and job["worker"] != lost
    assert job["outcome"]["annotations"] == 6 and not job["outcome"]["cached"]
    cluster = fresh.db[CLUSTERS].find_one()
    assert len(cluster["annotations"]) == 6  # 3 results + 3 derived, once
    assert len(server.requests) == 2


def test_a_dead_workers_job_is_taken_over_before_the_backlog_queued_before_it(
        fresh, mongo_uri, db_name):
    """Its due time is its lease's end, later than every job queued before: sorted by due
    alone, it waited for the whole backlog, running by a dead worker."""
    at = utc_now()
    fresh.db[JOBS].insert_many([{"kind": "lookup", "cluster_id": ObjectId(), "state": "queued",
                                 "attempts": 0, "due": at, "created": at, "updated": at}
                                for _ in range(3)])

    async def claims() -> tuple:
        client = AsyncMongoClient(mongo_uri)
        try:
            queue = JobQueue(client[db_name][JOBS], lease_s=0.5, max_attempts=5, backoff_s=1)
            dead = await queue.claim("dead")  # and never heard of again
            await dead.session.end_session()
            await asyncio.sleep(0.6)
            taken = await queue.claim("alive")
            await taken.session.end_session()
            return dead, taken
        finally:
            await client.close()

    dead, taken = asyncio.run(claims())
    assert taken.id == dead.id and taken.taken_over_from == "dead" and taken.attempts == 2


KILLED_INSIDE_ITS_TRANSACTION = """
import asyncio, sys
from pymongo import AsyncMongoClient
from percept_memory.ingest.jobs import JobQueue
from percept_memory.memory.schema import CLUSTERS, JOBS

async def main(uri, db):
    client = AsyncMongoClient(uri)
    queue = JobQueue(client[db][JOBS], lease_s=1, max_attempts=5, backoff_s=1)
    job = await queue.claim("doomed")
    await job.session.start_transaction()  # as the worker's append does: the cluster is held
    await client[db][CLUSTERS].update_one({"_id": job.cluster_id}, {"$set": {"held": 1}},
                                          session=job.session)
    print("open", flush=True)
    await asyncio.sleep(600)

asyncio.run(main(*sys.argv[1:]))
"""


def test_a_worker_killed_inside_its_transaction_holds_its_cluster_only_until_taken_over(
        fresh, mongo_uri, db_name):
    """The transaction a killed worker left open holds its cluster (and the cluster's object,
    which the consolidator of its map writes) until the server reaps it, 90 s later; the
    worker that takes the job over kills that session first, and finishes in seconds."""
    ingest(fresh, [scene_with_crops([cut(kitchen_frame(), MUESLI_BOX)], 1)])
    doomed = subprocess.Popen([sys.executable, "-c", KILLED_INSIDE_ITS_TRANSACTION, mongo_uri,
                               db_name], stdout=subprocess.PIPE, text=True,
                              env={**os.environ,
                                   "PYTHONPATH": str(Path(__file__).resolve().parents[1])})
    try:
        assert doomed.stdout.readline().strip() == "open"
    finally:
        doomed.send_signal(signal.SIGKILL)
        doomed.wait()
    time.sleep(1.2)  # its lease runs out
    start = time.monotonic()
    counts = asyncio.run(until_idle(settings_for(mongo_uri, db_name)))
    assert time.monotonic() - start < 20
    job = fresh.db[JOBS].find_one()
    assert counts["done"] == 1 and job["state"] == "done" and job["attempts"] == 2
    cluster = fresh.db[CLUSTERS].find_one()
    assert "held" not in cluster and cluster["annotations"]  # aborted; appended once


def test_graceful_shutdown_releases_unfinished_jobs(fresh, mongo_uri, db_name):
    server = LookupServer([(200, ANSWER, float("inf"))])

    async def stop_mid_lookup() -> Counter:
        stop = asyncio.Event()
        settings = settings_for(mongo_uri, db_name, lookup_url=server.url)
        worker = asyncio.create_task(run_worker(settings, backend="http", stop=stop,
                                                grace_s=0.2))
        while not server.requests:
            await asyncio.sleep(0.05)
        stop.set()
        return await worker

    try:
        ingest(fresh, [scene_with_crops([cut(kitchen_frame(), MUESLI_BOX)], 1)])
        counts = asyncio.run(stop_mid_lookup())
    finally:
        server.close()
    job = fresh.db[JOBS].find_one()
    assert counts["released"] == 1
    assert job["state"] == "queued" and job["attempts"] == 0 and "lease" not in job


# --- the perceptual-hash cache on real images ---------------------------------------------------


def test_hash_index_finds_the_nearest_within_the_radius():
    index = HashIndex()
    rng = np.random.default_rng(0)
    stored = [int(h) for h in rng.integers(0, 2**63, 5000)]
    index.add(stored)
    target = stored[1234] ^ 0b1011  # 3 bits off
    assert index.nearest(target, 3) == (stored[1234], 3)
    assert index.nearest(target, 2) is None
    assert index.nearest(2**64 - 1, 64) is not None  # unsigned hashes beyond int64 work
    assert index.size == 5000


def test_same_object_hits_the_cache_and_a_different_one_misses(fresh, mongo_uri, db_name):
    frame = kitchen_frame()
    original = cut(frame, MUESLI_BOX)
    again = same_object_again(frame, MUESLI_BOX)
    other = cut(frame, JUICE_CARTON)
    for variant in again:
        assert hamming(crop_phash(variant), crop_phash(original)) <= Settings().lookup_cache_radius

    class Counting(SimulatedService):
        calls = 0

        async def lookup(self, crop):
            Counting.calls += 1
            return answer(crop, 0)

    async def look_up_in_turn(clusters) -> list[dict]:
        from percept_memory.ingest.jobs import Job

        store = AsyncMemoryStore(AsyncMongoClient(mongo_uri, **CLIENT_OPTIONS), db_name,
                                 gridfs_threshold=Settings().gridfs_threshold)
        try:
            async with LookupCache(store.db[LOOKUP_CACHE], radius=10) as cache:
                lookup = Lookup(store, cache, Counting(), timeout_s=10)
                return [await lookup.run(Job(c.id, c.id, c.id, 1)) for c in clusters]
        finally:
            await store.close()

    scene = scene_with_crops([original, *again, other], 1)
    fresh.put_scene(scene)
    outcomes = asyncio.run(look_up_in_turn(scene.clusters))
    assert [o["cached"] for o in outcomes] == [False, True, True, True, True, False]
    assert Counting.calls == 2
    first = fresh.get_cluster(scene.clusters[0].id).annotations_of(WebLookup)
    for cluster in scene.clusters[1:5]:  # the same object got the same answer, from the cache
        reused = fresh.get_cluster(cluster.id).annotations_of(WebLookup)
        assert [(w.category, w.title) for w in reused] == [(w.category, w.title) for w in first]
        assert all(w.provenance.cached and w.provenance.hash_distance <= 10 for w in reused)


def test_cache_is_shared_between_workers_through_the_change_stream(fresh, mongo_uri, db_name):
    crop = cut(kitchen_frame(), MUESLI_BOX)
    findings = [Finding(category="logo", title="Kölln")]

    async def two_workers() -> list:
        one, two = (AsyncMongoClient(mongo_uri) for _ in range(2))
        try:
            async with LookupCache(one[db_name][LOOKUP_CACHE], 10) as first, \
                    LookupCache(two[db_name][LOOKUP_CACHE], 10) as second:
                await first.put("http", crop_phash(crop), findings, 850.0)
                for _ in range(100):
                    if (hit := await second.find("http", crop_phash(jpeg(crop, 75)))) is not None:
                        return hit.findings
                    await asyncio.sleep(0.02)
                return []
        finally:
            await one.close()
            await two.close()

    assert asyncio.run(two_workers()) == findings


# --- the backends -------------------------------------------------------------------------------


def test_simulated_service_reproduces_the_thesis_tables():
    rng = np.random.default_rng(1)
    latencies = np.array([sample_latency_s(rng) for _ in range(20000)])
    assert latencies.min() >= 0.504 and latencies.max() <= 2.314
    assert abs(latencies.mean() - 0.867) < 0.867 * 0.02  # table 5.6: mean 867 ms
    assert abs((latencies <= 0.9).mean() - (3 + 10 + 33 + 53) / 147) < 0.02
    crops = [np.random.default_rng(i).integers(0, 255, (32, 32, 3), np.uint8) for i in range(2000)]
    answers = [answer(crop, seed=0) for crop in crops]
    assert abs(np.mean([len(a) for a in answers]) - 371 / 147) < 0.1
    shares = Counter(f.category for a in answers for f in a)
    total = sum(shares.values())
    for category, count in CATEGORY_MIX.items():  # table 5.3
        assert abs(shares[category] / total - count / 371) < 0.025, category
    assert answer(crops[0], seed=0) == answers[0]  # the same crop, the same answer
    assert answer(crops[0], seed=1) != answers[0]


def test_catalogue_matches_real_products_and_nothing_else():
    catalogue = ProductCatalogue.load()
    products = json.loads((SHIPPED / "products.json").read_text())["products"]
    assert sum(f.stat().st_size for f in SHIPPED.iterdir()) < 1_000_000
    frames = {}
    for product in products:
        frame = frames.setdefault(product["source"]["frame"], cv2.imread(
            str(ROBOSHERLOCK / product["source"]["frame"]), cv2.IMREAD_COLOR))
        box = tuple(product["source"]["box"])
        shipped = cv2.imread(str(SHIPPED / product["image"]), cv2.IMREAD_COLOR)
        assert hamming(crop_phash(shipped), crop_phash(cut(frame, box))) <= 4  # cut as it says
        for variant in same_object_again(frame, box)[:1] + [
                cv2.warpAffine(cut(frame, box), cv2.getRotationMatrix2D(
                    (box[2] / 2, box[3] / 2), 8, 0.8), (box[2], box[3]))]:
            found = catalogue.match(variant)
            assert found and found[0].title == product["name"], product["id"]
            assert found[0].properties["category"] == product["category"]
    kitchen = frames["samples/kitchen/rgb_1522249987296654516.png"]
    for nothing in [(150, 330, 200, 120), (420, 20, 150, 120), (405, 165, 60, 80),
                    (100, 380, 200, 90)]:  # drawers, wall, the glass, the floor
        assert catalogue.match(cut(kitchen, nothing)) == [], nothing


def test_catalogue_backend_annotates_real_sample_clusters(fresh, mongo_uri, db_name):
    scenes = list(rgbd.read_samples(ROBOSHERLOCK / "samples" / "kitchen"))
    ingest(fresh, scenes)
    counts = asyncio.run(until_idle(settings_for(mongo_uri, db_name), backend="catalogue"))
    assert counts["done"] == len(scenes[0].clusters)
    names = {p.name for c in fresh.get_clusters([c.id for c in scenes[0].clusters]).values()
             for p in c.annotations_of(Product)}
    assert {"Kölln Müsli Knusper Honig-Nuss", "albi fruit juice"} <= names


# --- the queue as the CLI and the API show it ---------------------------------------------------


def test_failed_jobs_show_their_error_in_the_cli_and_the_api(fresh, mongo_uri, db_name):
    from click.testing import CliRunner
    from fastapi.testclient import TestClient

    from percept_memory.cli import main
    from percept_memory.webui.app import create_app

    server = LookupServer([(400, {"error": "not an image"}, 0)])
    try:
        ingest(fresh, [scene_with_crops([cut(kitchen_frame(), MUESLI_BOX)], 1)])
        asyncio.run(until_idle(settings_for(mongo_uri, db_name, lookup_url=server.url),
                               backend="http"))
    finally:
        server.close()
    client = TestClient(create_app(fresh, Settings()), base_url=LOCAL)
    body = client.get("/api/jobs", params={"state": "failed"}).json()
    assert body["counts"] == {"queued": 0, "running": 0, "done": 0, "failed": 1}
    (job,) = body["jobs"]
    assert job["state"] == "failed" and "HTTP 400" in job["error"]
    assert "not an image" in job["error"]
    counts_only = client.get("/api/jobs", params={"limit": 0}).json()  # not every job
    assert counts_only == {"counts": body["counts"], "jobs": []}
    bad = client.get("/api/jobs", params={"state": "lost", "limit": -1})
    assert bad.status_code == 422 and len(bad.json()["error"]["problems"]) == 2

    env = {"MONGODB_URI": mongo_uri, "PMEM_DB": db_name}
    shown = CliRunner().invoke(main, ["jobs", "--state", "failed"], env=env)
    assert shown.exit_code == 0 and "HTTP 400" in shown.stdout and "failed: 1" in shown.stdout
    again = CliRunner().invoke(main, ["jobs", "--retry-failed", "--json"], env=env)
    assert again.exit_code == 0 and json.loads(again.stdout)["counts"]["queued"] == 1
    none_left = CliRunner().invoke(main, ["jobs", "--retry-failed"], env=env)
    assert none_left.exit_code == 0 and "no failed job to queue again" in none_left.stderr
    assert "queued: 1" in none_left.stdout  # (the report: what the command is for)
    missing = CliRunner().invoke(main, ["worker", "--backend", "http"], env=env)
    assert missing.exit_code == 1 and "PMEM_LOOKUP_URL" in missing.output
