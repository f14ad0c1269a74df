"""The memory pipeline: exactly once, in order per map, failures held and shown, late scenes,
maps kept apart, any finite coordinates, and the belief built live equal to the one rebuilt."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections import Counter
from datetime import UTC, datetime, timedelta

import numpy as np
import pytest
from pymongo import MongoClient, monitoring
from pymongo.errors import ConfigurationError

from percept_memory.demo import kitchen_week
from percept_memory.ingest import synthetic
from percept_memory.ingest.service import IngestService, memory_pipeline
from percept_memory.memory import documents as docs
from percept_memory.memory.consolidation import Consolidation
from percept_memory.memory.known_objects import FIELDS
from percept_memory.memory.mongod import EmbeddedMongod
from percept_memory.memory.pipeline import (
    LeaseLost,
    Pipeline,
    request_rebuild,
    retry_held,
    status,
)
from percept_memory.memory.schema import (
    CALIBRATION,
    CATALOGUE,
    CATALOGUE_HISTORY,
    CATALOGUE_TRACKS,
    EVENTS,
    MAPS,
    OBJECTS,
    OUTBOX,
)
from percept_memory.memory.store import CLIENT_OPTIONS, MemoryStore
from percept_memory.memory.types import (
    Cluster,
    DifferentObject,
    Location,
    Scene,
    SemanticColor,
    Shape,
    SpatialVolume,
    WebLookup,
)
from percept_memory.queries.engine import QueryEngine
from percept_memory.webui.render import time_of

from .conftest import LOCAL, ingest_consolidated, served

# (the catalogue too: identity merges the objects it learns as one)
BELIEF = (OBJECTS, EVENTS, OUTBOX, MAPS, CALIBRATION, CATALOGUE, CATALOGUE_TRACKS,
          CATALOGUE_HISTORY)


@pytest.fixture
def empty(store):
    """The module's store with no scenes and no belief left by other tests."""
    for name in (*BELIEF, "scenes", "clusters", "jobs"):
        store.db[name].delete_many({})
    return store


@pytest.fixture(scope="module")
def week():
    return kitchen_week.generate(days=2)


def thing(x: float, colour: str, region: str = "table", y: float = 0.0) -> Cluster:
    return Cluster(annotations=[Location(region=region, position=(x, y, 0.8)),
                                SemanticColor(ratios={colour: 1.0}), Shape(shape="box")])


def looking_at(x0: float, x1: float, y: float = 0.0) -> SpatialVolume:
    return SpatialVolume(box_min=(x0, y - 1.0, 0.0), box_max=(x1, y + 1.0, 2.0))


def canonical_belief(store: MemoryStore) -> tuple[list, list]:
    """The objects and events, ids aside: an object is named by its first observation (cluster
    ids are the stored data's own), so two beliefs compare document for document."""
    first = {}
    for doc in store.clusters.find({"object_id": {"$ne": None}}, {"object_id": 1}).sort("_id"):
        first.setdefault(doc["object_id"], doc["_id"])

    def name(object_id):
        return first.get(object_id, "unobserved")

    objects = sorted(
        ({**{k: v for k, v in doc.items() if k != "_id"}, "key": name(doc["_id"])}
         for doc in store.db[OBJECTS].find()), key=lambda d: str(d["key"]))
    events = sorted(
        ({**{k: v for k, v in doc.items() if k not in ("_id", "object_id", "alternatives")},
          "key": name(doc["object_id"]),
          "alternatives": [{**a, "object_id": a["object_id"] and name(a["object_id"])}
                           for a in doc["alternatives"]]}
         for doc in store.db[EVENTS].find()),
        key=lambda d: (d["time"], str(d["key"]), d["explanation"]))
    return objects, events


def rebuilt(store: MemoryStore) -> tuple[list, list]:
    request_rebuild(store)
    memory_pipeline(store).drain(timeout=600)
    return canonical_belief(store)


# --- exactly once, in order ------------------------------------------------------------------


def test_a_scene_is_acknowledged_with_its_stages_pending_and_consolidated_once(empty, week):
    service = IngestService(empty)
    ids = service.ingest_batch(week.scenes[:10])
    assert empty.db[OUTBOX].count_documents({}) == 10  # stored: durable, not yet consolidated
    assert empty.db[EVENTS].count_documents({}) == 0
    assert service.settled(ids, timeout=60)
    clusters = sum(len(s.clusters) for s in week.scenes[:10])
    assert empty.db[OUTBOX].count_documents({}) == 0
    assert empty.db[EVENTS].count_documents({"cluster_id": {"$ne": None}}) == clusters
    assert empty.db["jobs"].count_documents({}) == clusters  # every crop queued for a lookup
    assert service.pipeline.run_once() == 0  # nothing is done twice
    (row,) = status(empty)["maps"]
    assert row == {**row, "map": kitchen_week.MAP, "pending": 0, "held": 0,
                   "consolidated_until_ns": week.scenes[9].timestamp}


def test_the_pipeline_thread_outlives_a_pass_that_fails(empty, week, monkeypatch, caplog):
    """Any error of a pass (a bug; a lease of 1e12 s once) ended the thread: the server went
    on storing scenes that no one consolidated."""
    service = IngestService(empty)
    service.pipeline.poll_s = 0.02
    passes = []
    real_pass = service.pipeline._pass

    def failing_once() -> int:
        passes.append(1)
        if len(passes) == 1:
            raise OverflowError("date value out of range")
        return real_pass()

    monkeypatch.setattr(service.pipeline, "_pass", failing_once)
    service.pipeline.start()
    try:
        ids = service.ingest_batch(week.scenes[:3])
        assert service.settled(ids, timeout=60)
    finally:
        service.pipeline.stop()
    assert "pipeline: a pass failed; retrying" in caplog.text


def test_the_pipeline_thread_gives_way_to_ingest_then_consolidates_everything_once(empty, week):
    service = IngestService(empty)
    service.pipeline.start()
    try:
        with service.pipeline.ingesting():  # another batch is being stored meanwhile
            ids = service.ingest_batch(week.scenes[:5])
            time.sleep(0.5)  # less than YIELD_S
            assert service.pipeline.pending() == 5
        assert service.settled(ids, timeout=60)
    finally:
        service.pipeline.stop()
    clusters = sum(len(s.clusters) for s in week.scenes[:5])
    assert empty.db[EVENTS].count_documents({"cluster_id": {"$ne": None}}) == clusters
    assert service.pipeline.run_once() == 0


class Commands(monitoring.CommandListener):
    """The commands a client sends while `on`, as (thread, name, collection), and the write
    concerns each (thread, name) asked for: pymongo's synchronous API sends a command from
    the thread that asked for it."""

    def __init__(self):
        self.seen, self.on, self.concerns = Counter(), False, {}

    def started(self, event):
        if self.on:
            thread, target = threading.current_thread().name, event.command.get(
                event.command_name)
            self.seen[thread, event.command_name, target if isinstance(target, str) else ""] += 1
            self.concerns.setdefault((thread, event.command_name), set()).add(
                tuple(sorted((event.command.get("writeConcern") or {}).items())))

    def succeeded(self, event):
        pass

    def failed(self, event):
        pass


def waited_for(mongo_uri, empty, week, threaded: bool) -> Commands:
    """The commands of storing 5 scenes one by one, each waited for (the map's first 3
    before: its first batches read more), by the pipeline's thread (looking for every map
    with work once a minute) or by the caller."""
    commands = Commands()
    client = MongoClient(mongo_uri, event_listeners=[commands], **CLIENT_OPTIONS)
    store = MemoryStore(client, empty.db.name, gridfs_threshold=empty.gridfs_threshold)
    service = IngestService(store)
    if threaded:
        service.pipeline.poll_s = 60.0
        service.pipeline.start()
    try:
        service.ingest_batch(week.scenes[:3], wait=60)
        commands.on = True
        for scene in week.scenes[3:8]:
            started = time.monotonic()
            assert service.ingest(scene, wait=60).created
            assert time.monotonic() - started < 5.0
        commands.on = False
    finally:
        service.pipeline.stop()
        client.close()
    return commands


def outbox_asks(commands: Commands) -> dict:
    caller = threading.current_thread().name
    return {(name, target): n for (thread, name, target), n in commands.seen.items()
            if thread == caller and target == OUTBOX and name != "insert"}


def test_a_scene_waited_for_costs_no_polling_and_no_lease_round_trips_of_its_own(
        mongo_uri, empty, week, monkeypatch):
    """The server's path: its consolidator thread works, the caller waits. The caller is told
    by the thread's commit and asks MongoDB nothing (with the poll for other processes' work
    made 5 s, a missed commit would show as an ask); the thread works on the map it was woken
    for, without looking for every map with work (it did when it started), takes the lease
    in one command and gives it back in the batch's own transaction."""
    monkeypatch.setattr("percept_memory.memory.pipeline.WAIT_POLL_S", 5.0)
    commands = waited_for(mongo_uri, empty, week, threaded=True)
    assert outbox_asks(commands) == {("find", OUTBOX): 5}  # only: is a scene of its map held?
    assert commands.seen["pmem-pipeline", "distinct", OUTBOX] == 0
    assert commands.seen["pmem-pipeline", "find", MAPS] == 0  # (maps to rebuild)
    lease = Counter({(name, target): n for (thread, name, target), n in commands.seen.items()
                     if thread == "pmem-pipeline" and target == MAPS and name != "find"})
    assert lease == {("findAndModify", MAPS): 5, ("update", MAPS): 5}  # taken; fence and end
    assert empty.db[MAPS].find_one({"_id": kitchen_week.MAP})["lease"] is None
    # the catalogue kept the tracks it wrote: the objects seen again are not read again
    assert commands.seen["pmem-pipeline", "find", CATALOGUE_TRACKS] == 0
    # the scene is journaled before it is acknowledged; the belief and the lease are not
    # waited for (redone from the outbox after a crash)
    stored = {c for (thread, name), concerns in commands.concerns.items()
              if name == "commitTransaction" and thread != "pmem-pipeline" for c in concerns}
    unjournaled = (("j", False), ("w", 1))
    assert stored and unjournaled not in stored
    for name in ("findAndModify", "commitTransaction"):
        assert commands.concerns["pmem-pipeline", name] == {unjournaled}


def test_a_scene_the_caller_consolidates_itself_is_asked_about_once(mongo_uri, empty, week):
    """The Python API's path, no consolidator thread: the caller works on its scene and knows
    by its own commit that it went through, so MongoDB is asked once whether it is pending
    (then it is read from the outbox to be worked on), not again after; and once whether a
    scene of its map is held."""
    commands = waited_for(mongo_uri, empty, week, threaded=False)
    assert outbox_asks(commands) == {("distinct", OUTBOX): 5, ("find", OUTBOX): 10,
                                     ("delete", OUTBOX): 5}
    assert empty.db[MAPS].find_one({"_id": kitchen_week.MAP})["lease"] is None


def test_scenes_are_consolidated_in_time_order_whatever_order_they_were_stored_in(empty, week):
    """Stored newest first but consolidated together: the pipeline takes them in time order,
    so the belief is the one of the scenes in time order."""
    scenes = week.scenes[:30]
    IngestService(empty).ingest_batch(list(reversed(scenes)))
    memory_pipeline(empty).drain(timeout=120)
    live = canonical_belief(empty)
    assert [e["time"] for e in live[1]] == sorted(e["time"] for e in live[1])
    assert rebuilt(empty) == live


def test_a_late_scene_rebuilds_its_map(empty, week):
    """A scene older than the newest consolidated one of its map: the map is rebuilt, so the
    belief is what consolidating all its scenes in time order gives."""
    service = IngestService(empty)
    scenes = week.scenes[:40]
    late = scenes.pop(20)
    service.ingest_batch(scenes, wait=120)
    service.ingest(late, wait=120)
    live = canonical_belief(empty)
    assert any(e["scene_id"] == late.id for e in live[1])
    assert rebuilt(empty) == live


def test_a_scene_waited_for_is_current_once_its_map_is_back_where_it_was(empty, week):
    """A late scene goes through first of its map's rebuild: its waiter was told "current"
    then, while the newer scenes were still to go through again (where-is answered from an
    hour before). The server's way, a consolidator thread, and the scenes waited for at once
    by another request."""
    service = IngestService(empty)
    service.pipeline.start()
    try:
        scenes = week.scenes[:70]
        late = scenes.pop(3)
        assert service.settled(service.ingest_batch(scenes), timeout=120)
        newest = status(empty)["maps"][0]["consolidated_until_ns"]
        assert service.settled([service.ingest(as_json(late))], timeout=120)
        (row,) = status(empty)["maps"]
        assert (row["consolidated_until_ns"], row["pending"], row["rebuilding"]) == (
            newest, 0, False)
    finally:
        service.pipeline.stop()


def test_a_scene_sent_again_before_it_was_consolidated_is_waited_for(empty, week):
    """A robot's retry after a timeout, with wait: the scene is stored (created false) but
    was still pending, and the answer came at once, its clusters in no belief yet."""
    service = IngestService(empty)
    first = service.ingest_batch(week.scenes[:8])
    assert empty.db[EVENTS].count_documents({}) == 0
    again = service.ingest(as_json(week.scenes[7]), wait=60)
    assert not again.created and again.scene_id == first[7].scene_id
    assert empty.db[EVENTS].count_documents({"cluster_id": {"$in": again.cluster_ids}}) == len(
        again.cluster_ids)


def test_the_belief_built_live_equals_the_rebuilt_one_with_lookups_in_between(empty, week):
    """Lookups append names while scenes keep coming; identity decides on the evidence the
    clusters arrived with, names sum every annotation: live == rebuilt, document for document."""
    service = IngestService(empty)
    for start in range(0, 90, 15):
        results = service.ingest_batch(week.scenes[start:start + 15], wait=120)
        for ids in [r for r in results if r.cluster_ids][::3]:  # as a lookup worker would
            empty.add_annotation(ids.cluster_ids[0], WebLookup(
                source="Goggles", service="simulated", category="product",
                title=f"Lookup {start}"))
    live = canonical_belief(empty)
    named = {label for o in live[0] for label in o["label_weights"]}
    assert {f"lookup {start}" for start in range(0, 90, 15)} <= named  # appended, counted
    assert rebuilt(empty) == live


def test_the_demo_data_built_live_equals_the_rebuilt_belief(store, week):
    """The real RoboSherlock dumps, the RGB-D samples and a kitchen week, each its own map."""
    from percept_memory.cli import demo_sources

    for name in (*BELIEF, "scenes", "clusters", "jobs"):
        store.db[name].delete_many({})
    for _source, scenes in demo_sources(days=2):
        ingest_consolidated(store, scenes)
    maps = set(store.db[MAPS].distinct("_id"))
    assert kitchen_week.MAP in maps
    assert len([m for m in maps if m.startswith("robosherlock/")]) == 2
    assert any(m.startswith("rgbd/") for m in maps)
    live = canonical_belief(store)
    assert len(live[0]) > 20
    assert rebuilt(store) == live


def test_a_scene_handed_over_is_what_identity_reads_back(empty, week):
    """Scenes a process made from JSON go to its consolidator as identity would read them back
    (no pixels, log or transforms): the kitchen week's, and synthetic ones with crops."""
    rng = np.random.default_rng(3)
    scenes = [*week.scenes[:30], *(synthetic.scene(rng, 10**18 + i, 3) for i in range(5))]
    results = IngestService(empty).ingest_batch([as_json(scene) for scene in scenes])
    handed = [empty.handed_over.take(ids.scene_id) for ids in results]
    read = list(Consolidation(elsewhere(empty))._scenes(
        [ids.scene_id for ids in results], None))
    assert len(read) == len(scenes) and all(handed)
    assert [h.model_dump_json() for h in handed] == [r.model_dump_json() for r in read]
    assert any(h.hypotheses for scene in handed for h in scene.clusters)


def test_scenes_handed_over_give_the_belief_a_rebuild_gives(empty, week, monkeypatch):
    """Posted one at a time as JSON and waited for, as a robot does over HTTP: none is read
    back to be consolidated, and the belief is the one a rebuild, reading every scene back,
    gives."""
    decode_scene, reads = docs.decode_scene, []
    monkeypatch.setattr(docs, "decode_scene", lambda *a: reads.append(a) or decode_scene(*a))
    service = IngestService(empty)
    for scene in week.scenes[:60]:
        assert service.ingest(as_json(scene), wait=60)
    assert not reads
    live = canonical_belief(empty)
    assert rebuilt(elsewhere(empty)) == live  # a process that stored none of them
    assert len(reads) == 60


def elsewhere(store: MemoryStore) -> MemoryStore:
    """The store as another process opens it: nothing handed over."""
    return MemoryStore(store.client, store.db.name, gridfs_threshold=store.gridfs_threshold)


def as_json(scene: Scene) -> dict:
    """The scene as a client sends it (ids are the server's to give)."""
    return json.loads(scene.model_dump_json(by_alias=True, exclude={"id"}))


# --- failures ----------------------------------------------------------------------------------


class Failing:
    """A stage that fails on the scenes it is told to (a bug, a bad document)."""

    name = "failing"
    belief = False

    def __init__(self, bad: set):
        self.bad = bad

    def apply(self, scene_ids, map_name, session):
        if self.bad & set(scene_ids):
            raise ValueError("cannot digest this scene")

    def reset(self, map_name):
        pass


def test_a_scene_that_keeps_failing_is_held_with_its_error_and_the_rest_go_on(empty, week):
    scenes = week.scenes[:12]
    service = IngestService(empty)
    ids = service.ingest_batch(scenes)
    bad = ids[4].scene_id
    stages = [Consolidation(empty), Failing({bad})]
    pipeline = Pipeline(empty, stages, backoff_s=0.01, max_attempts=3)
    pipeline.drain(timeout=60)
    report = status(empty)
    (held,) = report["held"]
    assert held["scene_id"] == str(bad) and held["attempts"] == 3
    assert "failing: ValueError: cannot digest this scene" in held["error"]
    assert report["maps"][0]["held"] == 1 and report["maps"][0]["pending"] == 0
    after = [ids[6].scene_id]  # went through, but its map's belief misses the held one
    assert pipeline.held(after) and not pipeline.wait(after, timeout=5)
    consolidated = set(empty.db[EVENTS].distinct("scene_id"))
    assert bad not in consolidated  # all or nothing: none of its stages' writes landed
    assert {i.scene_id for i in ids} - {bad} <= consolidated | {
        i.scene_id for i, s in zip(ids, scenes, strict=True) if not s.clusters}

    stages[1].bad.clear()  # fixed: the held scene goes through, late, so its map is rebuilt
    assert retry_held(empty) == 1
    pipeline.drain(timeout=60)
    assert not status(empty)["held"] and bad in set(empty.db[EVENTS].distinct("scene_id"))
    live = canonical_belief(empty)
    assert rebuilt(empty) == live


class Restarting(Failing):
    """A stage whose database is restarting for its first `times` calls: a mongod killed and
    started again answers, until it is a member of its replica set again, as a deployment
    without sessions (met by the kill -9 test)."""

    name = "restarting"

    def __init__(self, times: int):
        self.times = times

    def apply(self, scene_ids, map_name, session):
        if self.times:
            self.times -= 1
            raise ConfigurationError("Sessions are not supported by this MongoDB deployment")


def test_a_database_restarting_is_waited_out_and_counts_against_no_scene(empty, week):
    ids = IngestService(empty).ingest_batch(week.scenes[:6])
    pipeline = Pipeline(empty, [Consolidation(empty), Restarting(times=8)], backoff_s=0.01,
                        max_attempts=3)
    for _ in range(4):  # each pass tries twice: the second time on fresh connections
        with pytest.raises(ConfigurationError):
            pipeline.run_once()
    assert not status(empty)["held"]
    assert empty.db[OUTBOX].count_documents({"attempts": {"$gt": 0}}) == 0
    pipeline.drain(timeout=60)
    assert not empty.db[OUTBOX].count_documents({"_id": {"$in": [i.scene_id for i in ids]}})


def test_a_connection_handshaken_while_mongod_was_starting_is_replaced(empty, week):
    """After mongod's kill -9, a pooled connection opened before it was a primary again says
    "no sessions" for as long as it lives: the transaction drops such connections and goes on
    (the kill -9 test once waited 180 s on one)."""
    empty.db.command("ping")
    for server in empty.client._topology._servers.values():
        for connection in server.pool.conns:
            connection.supports_sessions = False  # what its handshake said while starting
    ids = IngestService(empty).ingest_batch(week.scenes[:2])
    assert empty.scenes.count_documents({"_id": {"$in": [i.scene_id for i in ids]}}) == 2


def test_the_cli_and_the_api_show_how_far_the_belief_is(empty, week, mongo_uri, db_name):
    from click.testing import CliRunner
    from fastapi.testclient import TestClient

    from percept_memory.cli import main
    from percept_memory.memory.settings import Settings
    from percept_memory.webui.app import create_app

    IngestService(empty).ingest_batch(week.scenes[:5])
    client = TestClient(create_app(empty, Settings(consolidator=False)), base_url=LOCAL)
    body = client.get("/api/pipeline").json()
    assert body["maps"][0]["pending"] == 5 and body["maps"][0]["consolidated_until"] is None
    env = {"MONGODB_URI": mongo_uri, "PMEM_DB": db_name}
    shown = CliRunner().invoke(main, ["pipeline", "--json"], env=env)
    assert shown.exit_code == 0 and '"pending": 5' in shown.stdout

    posted = client.post("/api/scenes?wait=belief",
                         json=week.scenes[5].model_dump(mode="json", exclude={"id"}))
    assert posted.status_code == 201 and posted.json()["belief"] == "current"
    body = client.get("/api/pipeline").json()
    assert body["maps"][0]["pending"] == 0
    assert body["maps"][0]["consolidated_until_ns"] == week.scenes[5].timestamp
    page = client.get("/pipeline")
    assert page.status_code == 200 and kitchen_week.MAP in page.text
    assert time_of(week.scenes[5].timestamp) in page.text  # as every page shows a time

    # who consolidates it: the lease's owner while the lease runs, no one once it ran out
    for until, shown in ((timedelta(seconds=30), "worker-7"), (-timedelta(seconds=1), None)):
        empty.db[MAPS].update_one({"_id": kitchen_week.MAP}, {"$set": {"lease": {
            "owner": "worker-7", "until": datetime.now(UTC) + until}}})
        assert status(empty)["maps"][0]["consolidator"] == shown
        listed = CliRunner().invoke(main, ["pipeline"], env=env)
        assert ("  by worker-7" in listed.stdout) == bool(shown)
    empty.db[MAPS].update_one({"_id": kitchen_week.MAP}, {"$set": {"lease": None}})

    # a scene of the map held: the belief is not current, and the answer says why
    held = IngestService(empty).ingest_batch(week.scenes[6:7])[0].scene_id
    Pipeline(empty, [Failing({held})], backoff_s=0, max_attempts=1).drain(timeout=30)
    assert status(empty)["held"][0]["scene_id"] == str(held)
    posted = client.post("/api/scenes?wait=belief",
                         json=week.scenes[7].model_dump(mode="json", exclude={"id"}))
    assert posted.status_code == 201 and posted.json()["belief"] == "held"


# --- maps and coordinates ----------------------------------------------------------------------


def test_observations_in_two_maps_are_never_one_object(empty):
    base = 5_000_000_000_000_000_000
    service = IngestService(empty)
    for i, site in enumerate(("home", "lab")):
        service.ingest(Scene(timestamp=base + i, robot="r", map=site, clusters=[thing(0.2, "red")],
                             view_region=looking_at(0.0, 1.0)), wait=30)
    objects = list(empty.db[OBJECTS].find())
    assert sorted(o["map"] for o in objects) == ["home", "lab"]
    assert {e["explanation"] for e in empty.db[EVENTS].find()} == {"appear"}
    engine = QueryEngine(empty)
    assert [o.map for o in engine.what_is_at(map="lab").objects] == ["lab"]


def test_lookalikes_asked_about_scene_after_scene_cost_one_read_each_a_batch(mongo_uri, empty):
    """Two red boxes seen together, then one of them alone, eight times: each scene asks
    whether the one seen could be the other (seen together once: no). Which scenes each was
    seen in is read once in the batch and then kept from its own writes, which go out once at
    its end: two distincts and one flush of events, not two and one a scene."""
    base = 5_200_000_000_000_000_000
    scenes = [Scene(timestamp=base, robot="r", map="twins", view_region=looking_at(0.0, 1.0),
                    clusters=[thing(0.2, "red"), thing(0.6, "red")])]
    scenes += [Scene(timestamp=base + i, robot="r", map="twins", clusters=[thing(0.2, "red")],
                     view_region=looking_at(0.0, 0.4)) for i in range(1, 9)]
    IngestService(empty).ingest_batch(scenes)
    commands = Commands()
    client = MongoClient(mongo_uri, event_listeners=[commands], **CLIENT_OPTIONS)
    try:
        store = MemoryStore(client, empty.db.name, gridfs_threshold=empty.gridfs_threshold)
        commands.on = True
        memory_pipeline(store).drain(timeout=60)
        commands.on = False
    finally:
        client.close()
    on_events = {name: n for (_, name, target), n in commands.seen.items() if target == EVENTS}
    assert on_events == {"distinct": 2, "insert": 1}
    assert [e["explanation"] for e in empty.db[EVENTS].find().sort("time")] == [
        "appear", "appear", "hidden"] + ["stay"] * 8


def test_a_split_that_comes_with_a_scene_holds_though_the_consolidator_knew_of_none(empty):
    """The consolidator keeps whether people split any objects with the map's objects (asked
    once); a split that arrives in a scene's own cluster is taken into account all the same."""
    base = 5_500_000_000_000_000_000
    service = IngestService(empty)  # one pipeline: its identity keeps the map's objects
    earlier = [service.ingest(Scene(timestamp=base + i, robot="r", map="split", clusters=[
        thing(0.2, "red")], view_region=looking_at(0.0, 1.0)), wait=30).cluster_ids[0]
        for i in range(2)]
    said = Cluster(annotations=[Location(region="table", position=(0.2, 0.0, 0.8)),
                                SemanticColor(ratios={"red": 1.0}), Shape(shape="box")])
    said.annotations.append(DifferentObject(split_off=[said.ensure_id()], apart_from=earlier,
                                            author="ana", time=base))
    service.ingest(Scene(timestamp=base + 2, robot="r", map="split", clusters=[said],
                         view_region=looking_at(0.0, 1.0)), wait=30)
    objects = [empty.clusters.find_one({"_id": c})["object_id"] for c in [*earlier, said.id]]
    assert objects[0] == objects[1] != objects[2]


def test_any_finite_coordinates_work(empty):
    """UTM-sized and astronomically large coordinates: stored, consolidated, answered."""
    base = 6_000_000_000_000_000_000
    service = IngestService(empty)
    for i, (x, y) in enumerate([(455_000.0, 5_400_000.0), (1e300, -1e300)]):
        for step in range(2):
            ids = service.ingest(Scene(
                timestamp=base + 10 * i + step, robot="utm", map=f"far {i}",
                clusters=[thing(x, "blue", y=y)], view_region=looking_at(x - 1, x + 1, y)),
                wait=30)
            assert ids.created
    assert not status(empty)["held"]
    explanations = [e["explanation"] for e in empty.db[EVENTS].find().sort("time")]
    assert explanations == ["appear", "stay", "appear", "stay"]
    (where,) = QueryEngine(empty).where_is(str(ids.cluster_ids[0]))
    assert where.state == "present" and where.position == (1e300, -1e300, 0.8)


# --- one writer per map, whoever dies --------------------------------------------------------


def test_one_consolidator_per_map_and_a_stale_one_cannot_commit(empty, week):
    IngestService(empty).ingest_batch(week.scenes[:3])
    first, second = (Pipeline(empty, [Consolidation(empty)], lease_s=0.2) for _ in range(2))
    with empty.client.start_session() as mine, empty.client.start_session() as theirs:
        lease = first._acquire(kitchen_week.MAP, mine)
        assert lease is not None and second._acquire(kitchen_week.MAP, theirs) is None
        time.sleep(0.3)  # the first pauses past its lease: the second takes the map over
        assert second._acquire(kitchen_week.MAP, theirs) is not None
        entries = first._next(kitchen_week.MAP, 3)
        with pytest.raises(LeaseLost):
            first._apply(kitchen_week.MAP, lease["lease"]["token"], entries, mine)
    assert empty.db[EVENTS].count_documents({}) == 0  # fenced: nothing of it landed


def test_consolidators_taking_turns_on_a_map_keep_the_belief_a_rebuild_gives(empty, week):
    """Each consolidator keeps the map's objects and places in memory (memory/known_objects.py);
    a copy that missed a write (by another consolidator, or by its own transaction that did
    not commit) must be read again, or it would decide on a stale belief."""
    service = IngestService(empty)
    first, second = (Pipeline(empty, [Consolidation(empty)], batch=5) for _ in range(2))
    failing = Failing(set())
    broken = Pipeline(empty, [Consolidation(empty), failing], batch=5, backoff_s=0.01)
    scenes = week.scenes[:60]
    for turn, start in enumerate(range(0, len(scenes), 10)):
        ids = service.ingest_batch(scenes[start:start + 10])
        if turn % 2:  # its batch of 5 is consolidated in memory, then its transaction fails
            failing.bad = {ids[3].scene_id}
            broken.run_once()
            failing.bad.clear()
        (first if turn % 3 else second).drain(timeout=60)
    known = first.stages[0]._known[kitchen_week.MAP]
    places = known.places
    stored = {doc["_id"]: doc["position"] for doc in empty.db[OBJECTS].find(
        {"state": {"$ne": "disappeared"}})}
    assert {i: list(places.xyz[r]) for i, r in places.rows.items() if places.live[r]} == stored
    assert known.docs == {doc["_id"]: doc for doc in empty.db[OBJECTS].find(
        {}, dict.fromkeys(FIELDS, 1))}
    assert rebuilt(empty) == canonical_belief(empty)


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def _consolidator(uri: str, db: str) -> subprocess.Popen:
    """`pmem consolidate` in a process of its own, once it says it is consolidating; its log
    is read as it comes (`process.log`, complete once `process.reader` ended): a pipe nobody
    reads blocks a process that logs much, as a consolidator does while mongod is down."""
    env = {**os.environ, "MONGODB_URI": uri, "PMEM_DB": db, "PMEM_MAP_LEASE_S": "2"}
    process = subprocess.Popen([sys.executable, "-m", "percept_memory", "consolidate"],
                               env=env, stderr=subprocess.PIPE, text=True)
    assert "consolidating" in process.stderr.readline()
    process.log = []  # type: ignore[attr-defined]
    process.reader = threading.Thread(  # type: ignore[attr-defined]
        target=process.log.extend, args=(process.stderr,), daemon=True)
    process.reader.start()
    return process


def _acknowledged(service: IngestService, scene: Scene):
    """Ingest as a robot does: retry until the memory acknowledges the scene."""
    deadline = time.monotonic() + 120
    while True:
        try:
            return service.ingest(scene)
        except Exception:  # the database is down: the scene was not acknowledged, send again
            if time.monotonic() > deadline:
                raise
            time.sleep(0.5)


def test_kill_9_of_the_consolidator_and_of_mongod_loses_nothing_and_doubles_nothing(
        tmp_path, week):
    """A robot streams scenes; a third of the way the consolidator process is killed with
    SIGKILL (at work: most likely inside a transaction, which stays open on the server), and
    the one started next takes the map over as soon as the lease runs out, not once the server
    gives up on the dead one's transaction (a minute, reaped later: 90 s measured); two thirds
    of the way mongod is killed: afterwards every acknowledged scene is consolidated exactly
    once."""
    mongod = EmbeddedMongod(tmp_path / "mongod", _free_port(), cache_gb=0.25, oplog_mb=64)
    uri = mongod.start()
    db = "crash"
    client = MongoClient(uri, **CLIENT_OPTIONS, serverSelectionTimeoutMS=2000)
    store = MemoryStore(client, db, gridfs_threshold=128 * 1024)
    store.prepare()
    service = IngestService(store)
    consolidator = _consolidator(uri, db)
    acknowledged = []
    third = len(week.scenes) // 3
    try:
        for i, scene in enumerate(week.scenes):
            acknowledged.append(_acknowledged(service, scene))
            if i == third:
                consolidator.send_signal(signal.SIGKILL)
                consolidator.wait()
                consolidator = _consolidator(uri, db)
                _consolidated(store, acknowledged, 20, consolidator)  # (the lease is 2 s)
            if i == 2 * third:
                killed = mongod.status()["pid"]
                os.kill(killed, signal.SIGKILL)
                time.sleep(1)
                mongod.start()
                assert mongod.status()["pid"] != killed
        _consolidated(store, acknowledged, 180, consolidator)
        clusters = [c for ids in acknowledged for c in ids.cluster_ids]
        events = list(store.db[EVENTS].find({"cluster_id": {"$ne": None}}, {"cluster_id": 1}))
        assert sorted(e["cluster_id"] for e in events) == sorted(clusters)  # each exactly once
        observed = sum(o["observations"] for o in store.db[OBJECTS].find())
        assert observed == len(clusters)
        assert store.clusters.count_documents({"object_id": None}) == 0
        assert store.db["jobs"].count_documents({}) == len(clusters)
        live = canonical_belief(store)
    finally:
        consolidator.send_signal(signal.SIGTERM)
        consolidator.wait(timeout=30)
    assert rebuilt(store) == live
    client.close()
    mongod.stop()


def _consolidated(store: MemoryStore, acknowledged: list, within_s: float,
                  consolidator: subprocess.Popen) -> None:
    """Wait until the acknowledged scenes went through the pipeline: at most `within_s` (the
    consolidator's log in the message when not)."""
    scenes = [ids.scene_id for ids in acknowledged]
    deadline = time.monotonic() + within_s
    while store.db[OUTBOX].count_documents({"_id": {"$in": scenes}}):
        assert time.monotonic() < deadline, (f"not consolidated within {within_s} s; the "
                                             f"consolidator said: {''.join(consolidator.log)}")
        time.sleep(0.2)


def test_a_client_that_stalls_in_its_body_does_not_hold_the_belief_back(empty, week):
    """Reading a request's body counted as ingest under way for as long as it took: the
    consolidator gave way a second before every 4 scenes, for every map (60 scenes: 15.6 s
    instead of 0.3 s); now only the parts that come count."""
    import httpx2

    from percept_memory.memory.settings import Settings
    from percept_memory.webui.app import create_app

    with served(create_app(empty, Settings())) as url:
        port = int(url.rsplit(":", 1)[1])
        with socket.create_connection(("127.0.0.1", port)) as stalled:
            stalled.sendall(b"POST /api/scenes HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: "
                            b"application/json\r\nContent-Length: 1000\r\n\r\n[")
            time.sleep(0.3)
            started = time.monotonic()
            answer = httpx2.post(f"{url}/api/scenes?wait=belief", timeout=60, json=[
                s.model_dump(mode="json", exclude={"id"}) for s in week.scenes[:40]])
            assert answer.json()["belief"] == "current"
            assert time.monotonic() - started < 5  # (before: over 10 s, 1 s a batch of 4)


def test_the_pipeline_thread_stops_between_batches_leaving_the_backlog_in_the_outbox(
        empty, week):
    """Stopping, it went on until the whole backlog was consolidated (a server's SIGTERM took
    57 s for 11,620 scenes, past docker's grace period); the rest is durable in the outbox,
    and consolidated as it would have been by whoever comes next."""
    service = IngestService(empty)
    service.ingest_batch(week.scenes[:120])
    service.pipeline.batch = 4
    service.pipeline.start()
    try:
        deadline = time.monotonic() + 60
        while service.pipeline.pending() > 110:
            assert time.monotonic() < deadline
            time.sleep(0.01)
    finally:
        started = time.monotonic()
        service.pipeline.stop()
    assert time.monotonic() - started < 2.0
    assert service.pipeline.pending() > 0  # left for later
    assert empty.db[MAPS].find_one({"_id": kitchen_week.MAP})["lease"] is None
    memory_pipeline(empty).drain(timeout=120)
    assert rebuilt(empty) == canonical_belief(empty)


def test_a_consolidator_process_stops_cleanly_on_sigterm(mongo_uri, db_name):
    process = _consolidator(mongo_uri, db_name)
    process.send_signal(signal.SIGTERM)
    assert process.wait(timeout=30) == 0
    process.reader.join(timeout=10)
    assert "consolidator stopped" in "".join(process.log)



def test_a_scene_log_of_stored_scenes_is_decided_alike_again(empty, week, mongo_uri, db_name,
                                                             tmp_path):
    """Scenes written from the memory as a scene log hold the lookups enrichment appended
    since; imported again, those did not come with the scenes (`arrived`), so identity decides
    on what it decided on the first time: the same belief (it was 2,056 events for 2,062 on
    the demo's data, the lookups taken as the clusters' own evidence)."""
    from click.testing import CliRunner

    from percept_memory.cli import main
    from percept_memory.ingest.scene_log import write_scene_log

    ingest_consolidated(empty, week.scenes[:40])
    looked_up = [doc["_id"] for doc in empty.clusters.find({}, {"_id": 1}).sort("_id")][::3]
    for cluster_id in looked_up:
        empty.add_annotation(cluster_id, WebLookup(category="product", title="Nutella jar",
                                                   service="simulated"))
    scenes = [empty.get_scene(doc["_id"])
              for doc in empty.scenes.find({}, {"_id": 1}).sort("timestamp")]
    assert write_scene_log(scenes, tmp_path) == 40
    copy = f"{db_name}_copy"
    try:
        done = CliRunner().invoke(main, ["import", "scene-log", str(tmp_path)],
                                  env={"MONGODB_URI": mongo_uri, "PMEM_DB": copy})
        assert done.exit_code == 0, done.output
        copied = MemoryStore(MongoClient(mongo_uri, **CLIENT_OPTIONS), copy, gridfs_threshold=2048)

        def arrived(store):
            return {doc["_id"]: docs.arrived(doc) for doc in store.clusters.find()}
        assert arrived(copied) == arrived(empty)
        assert sum(n < len(c.annotations) for s in scenes for c in s.clusters
                   for n in [c.arrived or len(c.annotations)]) == len(looked_up)
        assert canonical_belief(copied) == canonical_belief(empty)
    finally:
        MongoClient(mongo_uri).drop_database(copy)


def test_a_belief_answer_read_while_its_map_is_rebuilt_says_so(empty, week, mongo_uri, db_name):
    """A late scene rebuilds its map's belief from the start; meanwhile where-is answered
    from a belief months behind (4,000 scenes: a minute) with nothing to tell it apart."""
    from click.testing import CliRunner
    from fastapi.testclient import TestClient

    from percept_memory.cli import main
    from percept_memory.memory.settings import Settings
    from percept_memory.webui.app import create_app
    from percept_memory.webui.queries import REBUILDING_HEADER

    ingest_consolidated(empty, week.scenes[:20])
    client = TestClient(create_app(empty, Settings(consolidator=False)), base_url=LOCAL)
    env = {"MONGODB_URI": mongo_uri, "PMEM_DB": db_name}

    def told() -> tuple[str | None, str | None, str | None]:
        answer = client.get("/api/where-is", params={"x": "ketchup"})
        other = client.get("/api/clusters", params={"limit": 1})  # not the belief's
        shown = CliRunner().invoke(main, ["query", "what-is-at", "--map", kitchen_week.MAP],
                                   env=env)
        warning = next((line for line in shown.stderr.splitlines()
                        if line.startswith("Warning:")), None)
        return answer.headers.get(REBUILDING_HEADER), other.headers.get(REBUILDING_HEADER), warning

    assert told() == (None, None, None)
    request_rebuild(empty)
    header, other, warning = told()
    assert header == kitchen_week.MAP and other is None
    assert "is being rebuilt" in client.get("/map", params={"map": kitchen_week.MAP}).text
    assert warning == (f"Warning: the belief of {kitchen_week.MAP} is being rebuilt: this answer "
                       "holds only the scenes consolidated so far (`pmem pipeline` shows how "
                       "far)")
    memory_pipeline(empty).drain(timeout=600)
    assert told() == (None, None, None)
    assert "is being rebuilt" not in client.get("/map", params={"map": kitchen_week.MAP}).text


def test_a_rejection_takes_out_a_cluster_this_process_stored_from_json(empty, week):
    """Scenes made here from JSON are handed to the consolidator as they came (store.
    handed_over); the rebuild a rejection asks for read that copy again, without the
    rejection, and kept the rejected cluster in the belief (through HTTP: every rejection)."""
    from percept_memory.memory import curation

    service = IngestService(empty)
    service.ingest_batch([as_json(scene) for scene in week.scenes[:12]], wait=60)
    cluster_id = empty.scenes.find_one({"timestamp": week.scenes[10].timestamp})["clusters"][0]
    assert empty.clusters.find_one({"_id": cluster_id})["object_id"] is not None
    curation.reject(empty, cluster_id, author="ana")
    memory_pipeline(empty).drain(timeout=120)
    assert empty.clusters.find_one({"_id": cluster_id}).get("object_id") is None
    assert not empty.db[EVENTS].find_one({"cluster_id": cluster_id})


def test_an_object_not_yet_made_again_by_a_rebuild_is_a_404_that_says_so(empty, week):
    """Midway through a rebuild its page redirected to itself (its clusters still name it,
    the object is not made again yet: a redirect loop), and where-is of its id answered
    'no object or cluster', though both are."""
    from fastapi.testclient import TestClient

    from percept_memory.memory.settings import Settings
    from percept_memory.webui.app import create_app
    from percept_memory.webui.queries import REBUILDING_HEADER

    ingest_consolidated(empty, week.scenes[:20])
    late = empty.db[OBJECTS].find_one(sort=[("first_seen", -1)])["_id"]
    client = TestClient(create_app(empty, Settings(consolidator=False)), base_url=LOCAL,
                        follow_redirects=False)
    request_rebuild(empty)  # and, as the rebuild begins, the map's objects forgotten
    empty.db[OBJECTS].delete_one({"_id": late})
    page = client.get(f"/objects/{late}")
    assert page.status_code == 404 and "is being rebuilt" in page.text
    answer = client.get("/api/where-is", params={"x": str(late)})
    assert answer.status_code == 404 and answer.headers[REBUILDING_HEADER] == kitchen_week.MAP
    assert (f"the belief of map {kitchen_week.MAP} is being rebuilt"
            in answer.json()["error"]["message"])
    memory_pipeline(empty).drain(timeout=600)
    assert client.get(f"/objects/{late}").status_code == 200
    assert client.get("/api/where-is", params={"x": str(late)}).status_code == 200
