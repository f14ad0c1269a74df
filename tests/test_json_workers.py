"""Large JSON bodies prepared by worker processes (ingest/json_batches.py): stored exactly as
the in-process path stores them, all or nothing, problems named by their place in the body."""

from __future__ import annotations

import json
import multiprocessing

import bson
import numpy as np
import pytest
from bson import ObjectId
from fastapi.testclient import TestClient

from percept_memory.ingest import synthetic
from percept_memory.ingest.json_batches import PARALLEL_BYTES
from percept_memory.ingest.service import IngestService
from percept_memory.memory.settings import Settings
from percept_memory.memory.store import MemoryStore
from percept_memory.webui.app import create_app

from .conftest import LOCAL
from .test_store import snapshot

STAMP = 1_750_000_000_000_000_000


def body_of(kitchen_rgb, first: int, count: int = 24) -> list[dict]:
    rng = np.random.default_rng(first)
    return [json.loads(synthetic.scene(rng, STAMP + (first + i) * 10**9, 6, kitchen_rgb)
                       .model_dump_json(by_alias=True)) for i in range(count)]


def encoded(scenes: list[dict]) -> bytes:
    body = json.dumps(scenes).encode()
    assert len(body) >= PARALLEL_BYTES  # large enough for the workers
    return body


def as_ndjson(scenes: list[dict]) -> bytes:
    body = b"".join(json.dumps(scene).encode() + b"\n" for scene in scenes)
    assert len(body) >= PARALLEL_BYTES
    return body


@pytest.fixture(scope="module")
def client(store):
    settings = Settings(ingest_processes=2, consolidator=False, max_request_mb=64)
    with TestClient(create_app(store, settings), base_url=LOCAL) as client:
        yield client


def post(client, body: bytes, media_type: str = "application/json"):
    return client.post("/api/scenes", content=body, headers={"content-type": media_type})


def without_ids(value):
    """A document with every id blanked (ids are made afresh by each store)."""
    if isinstance(value, dict):
        return {k: without_ids(v) for k, v in value.items()}
    if isinstance(value, list):
        return [without_ids(v) for v in value]
    return None if isinstance(value, ObjectId) else value


@pytest.mark.parametrize("media_type", ["application/json", "application/x-ndjson"])
def test_the_workers_store_what_the_in_process_path_stores(client, store, kitchen_rgb,
                                                           media_type):
    scenes = body_of(kitchen_rgb, 0 if media_type == "application/json" else 50)
    body = encoded(scenes) if media_type == "application/json" else as_ndjson(scenes)
    answer = post(client, body, media_type)
    assert answer.status_code == 201, answer.text
    ids = [ObjectId(s["scene_id"]) for s in answer.json()["scenes"]]
    assert len(ids) == 24 and all(s["created"] for s in answer.json()["scenes"])
    assert len(multiprocessing.active_children()) == 2  # the workers prepared them
    other = MemoryStore(store.client, store.db.name + "_inproc",
                        gridfs_threshold=store.gridfs_threshold)
    try:
        other.prepare()
        IngestService(other, settings=Settings(ingest_processes=1)).ingest_json(encoded(scenes))
        ours = {"scenes": {"_id": {"$in": ids}}, "clusters": {"scene_id": {"$in": ids}},
                "outbox": {"_id": {"$in": ids}}}
        for name, selected in ours.items():  # (ids made in two processes: not in time order)
            made = sorted(bson.encode(without_ids(d)) for d in store.db[name].find(selected))
            assert made == sorted(bson.encode(without_ids(d)) for d in other.db[name].find())
            assert len(made) == (24 * 6 if name == "clusters" else 24), name
        assert [store.get_scene(i).timestamp for i in ids] == [s["timestamp"] for s in scenes]
    finally:
        store.client.drop_database(other.db.name)


@pytest.mark.parametrize("media_type", ["application/json", "application/x-ndjson"])
def test_posting_it_again_stores_nothing_twice(client, store, kitchen_rgb, media_type):
    scenes = body_of(kitchen_rgb, 100 if media_type == "application/json" else 150)
    body = encoded(scenes) if media_type == "application/json" else as_ndjson(scenes)
    first = post(client, body, media_type).json()["scenes"]
    before = snapshot(store)
    again = post(client, body, media_type)  # (the workers' write is refused: made here)
    assert again.status_code == 201
    assert [s["scene_id"] for s in again.json()["scenes"]] == [s["scene_id"] for s in first]
    assert not any(s["created"] for s in again.json()["scenes"])
    assert snapshot(store) == before


@pytest.mark.parametrize("media_type", ["application/json", "application/x-ndjson"])
def test_a_scene_twice_in_a_large_body_is_stored_once(client, store, kitchen_rgb, media_type):
    """The same scene first and last: a 409 'already used by another document ... give new
    objects no id', though a small body stored it once (the two were prepared apart)."""
    scenes = body_of(kitchen_rgb, 300 if media_type == "application/json" else 350)
    scenes.append(scenes[0])
    body = encoded(scenes) if media_type == "application/json" else as_ndjson(scenes)
    answer = post(client, body, media_type)
    assert answer.status_code == 201, answer.text
    stored = answer.json()["scenes"]
    assert stored[-1] == {**stored[0], "created": False} and stored[0]["created"]
    assert len({s["scene_id"] for s in stored}) == len(scenes) - 1
    assert store.scenes.count_documents(
        {"_id": {"$in": [ObjectId(s["scene_id"]) for s in stored]}}) == len(scenes) - 1


def test_problems_in_any_part_are_named_by_their_place_and_nothing_is_stored(
        client, store, kitchen_rgb):
    scenes = body_of(kitchen_rgb, 200)
    scenes[2]["timestamp"] = -1  # in the first worker's part
    scenes[21]["clusters"][0]["annotations"][1]["confidence"] = "high"  # in the second's
    before = snapshot(store)
    answer = post(client, encoded(scenes))
    assert answer.status_code == 422
    problems = answer.json()["error"]["problems"]
    assert {(p["item"], p["path"]) for p in problems} == {
        (2, "timestamp"), (21, "clusters.0.annotations.1.confidence")}
    assert snapshot(store) == before


def test_ndjson_problems_in_any_part_are_named_by_scene_and_line_and_nothing_is_stored(
        client, store, kitchen_rgb):
    lines = [json.dumps(scene).encode() for scene in body_of(kitchen_rgb, 250)]
    lines[1] = lines[1][:-1]  # not JSON: in the first part
    lines[22] = lines[22].replace(b'"timestamp": ', b'"timestamp": -')  # in the last
    body = b"\n".join(lines)
    assert len(body) >= PARALLEL_BYTES
    before = snapshot(store)
    answer = post(client, body, "application/x-ndjson")
    assert answer.status_code == 422
    problems = answer.json()["error"]["problems"]
    assert [(p["item"], p["path"]) for p in problems] == [(1, ""), (22, "timestamp")]
    assert problems[0]["message"].startswith("line 2 is not valid JSON")
    assert snapshot(store) == before


def test_a_large_body_that_is_not_json_is_a_422(client):
    answer = post(client, b"[" + b"1," * PARALLEL_BYTES)
    assert answer.status_code == 422
    assert "not valid JSON" in answer.json()["error"]["message"]


def test_a_worker_that_died_costs_nothing_but_time(client, store, kitchen_rgb):
    post(client, encoded(body_of(kitchen_rgb, 300)))  # the workers run
    for worker in multiprocessing.active_children():
        worker.kill()
        worker.join()
    body = encoded(body_of(kitchen_rgb, 400))
    answer = post(client, body)  # made here, this once
    assert answer.status_code == 201, answer.text
    assert all(s["created"] for s in answer.json()["scenes"])
    assert post(client, encoded(body_of(kitchen_rgb, 500))).status_code == 201  # afresh
    assert len(multiprocessing.active_children()) == 2


@pytest.mark.parametrize("media_type", ["application/json", "application/x-ndjson"])
@pytest.mark.parametrize("apart", [1, 19], ids=["one part", "two parts"])
def test_two_different_scenes_at_one_robot_and_time_are_refused(client, store, kitchen_rgb,
                                                                media_type, apart):
    """Made in one worker's part or in two, a body with two different scenes of one robot
    and time is a 409 naming them, and nothing of it is written (the second was dropped)."""
    scenes = body_of(kitchen_rgb, 300 + apart + (100 if media_type.endswith("ndjson") else 0))
    scenes[3 + apart]["timestamp"] = scenes[3]["timestamp"]
    before = snapshot(store)
    body = encoded(scenes) if media_type == "application/json" else as_ndjson(scenes)
    answer = post(client, body, media_type)
    assert answer.status_code == 409, answer.text
    assert "two different scenes at timestamp" in answer.json()["error"]["message"]
    assert snapshot(store) == before
