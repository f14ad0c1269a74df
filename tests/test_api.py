"""The HTTP API: POST /api/scenes and the scene schema, on the real store."""

from __future__ import annotations

import json

import pytest
from bson import ObjectId
from fastapi.testclient import TestClient

from percept_memory.memory.settings import Settings
from percept_memory.webui.app import create_app

from .conftest import LOCAL
from .test_ingest import valid_scene
from .test_store import snapshot

STAMP = 1_700_000_000_000_000_000


@pytest.fixture(scope="module")
def client(store):
    return TestClient(create_app(store, Settings(max_request_mb=1)), base_url=LOCAL)


def test_schema_describes_every_annotation_kind(client):
    schema = client.get("/api/schema/scene").json()
    kinds = {k["properties"]["_type"]["const"] for k in schema["$defs"]["Annotation"]["oneOf"]}
    assert {"pm.annotation.Classification", "pm.annotation.WebLookup"} <= kinds
    assert "/api/scenes" in client.get("/openapi.json").json()["paths"]


def test_post_one_scene_then_again(client, store):
    scene = valid_scene(seed=1, timestamp=STAMP)
    first = client.post("/api/scenes", json=scene)
    assert first.status_code == 201, first.text
    (stored,) = first.json()["scenes"]
    assert stored["created"] and len(stored["cluster_ids"]) == 2
    assert store.get_scene(ObjectId(stored["scene_id"])).timestamp == STAMP
    again = client.post("/api/scenes", json=scene).json()["scenes"][0]
    assert again["scene_id"] == stored["scene_id"] and not again["created"]


def test_every_annotation_posted_is_named_by_the_id_at_its_place(client, store):
    """Annotations of another program's types get ids too: the answer's annotation_ids were
    those of ours alone, so a client's i-th id named another annotation."""
    scene = valid_scene(seed=2, timestamp=STAMP + 5)
    grip = {"_type": "acme.annotation.Grip", "force": 3.5}
    kept = scene["clusters"][0]["annotations"][:2]
    scene["clusters"][0]["annotations"] = [grip, kept[0], dict(grip, force=4.0), kept[1]]
    first = client.post("/api/scenes", json=scene).json()["scenes"][0]
    ids = first["annotation_ids"][0]
    stored = store.clusters.find_one({"_id": ObjectId(first["cluster_ids"][0])})["annotations"]
    assert len(ids) == 4 and [str(a["_id"]) for a in stored] == ids
    assert [a.get("force") for a in stored] == [3.5, None, 4.0, None]
    again = client.post("/api/scenes", json=scene).json()["scenes"][0]
    assert not again["created"] and again["annotation_ids"][0] == ids
    scene["timestamp"] = STAMP + 500  # an id of null is none; one id twice names nothing
    scene["clusters"][0]["annotations"][0]["_id"] = None
    given = client.post("/api/scenes", json=scene).json()["scenes"][0]["annotation_ids"][0]
    assert ObjectId.is_valid(given[0]) and len(set(given)) == 4
    twice = {"$oid": str(ObjectId())}
    scene["timestamp"] = STAMP + 501
    scene["clusters"][0]["annotations"][0]["_id"] = scene["clusters"][0]["annotations"][2][
        "_id"] = twice
    refused = client.post("/api/scenes", json=scene)
    assert refused.status_code == 422 and "is given twice" in refused.text


def test_a_stored_scene_and_cluster_are_read_back_as_json(client, store):
    """A robot could read back what it stored only as HTML pages or through Python."""
    scene = valid_scene(seed=6, timestamp=STAMP + 6)
    (stored,) = client.post("/api/scenes", json=scene).json()["scenes"]
    back = client.get(f"/api/scenes/{stored['scene_id']}")
    assert back.status_code == 200 and back.json()["_id"] == stored["scene_id"]
    again = client.post("/api/scenes", json=back.json()).json()["scenes"][0]
    assert not again["created"] and again["cluster_ids"] == stored["cluster_ids"]
    cluster = client.get(f"/api/clusters/{stored['cluster_ids'][0]}").json()
    assert cluster["scene_id"] == stored["scene_id"]
    assert [a["_id"] for a in cluster["annotations"]] == stored["annotation_ids"][0]
    missing = client.get(f"/api/scenes/{ObjectId()}")
    assert missing.status_code == 404 and "error" in missing.json()
    assert client.get("/api/clusters/nope").status_code == 422


def test_post_a_batch(client):
    batch = [valid_scene(seed=i, timestamp=STAMP + 10 + i) for i in range(3)]
    response = client.post("/api/scenes", json=batch)
    assert response.status_code == 201
    assert [s["created"] for s in response.json()["scenes"]] == [True, True, True]


def test_invalid_scenes_get_422_with_every_problem_and_nothing_is_written(client, store):
    bad = valid_scene(seed=4, timestamp=STAMP + 20)
    bad["clusters"][0]["annotations"][1]["confidence"] = 7
    del bad["timestamp"]
    before = snapshot(store)
    response = client.post("/api/scenes", json=[valid_scene(seed=5, timestamp=STAMP + 21), bad])
    assert response.status_code == 422
    error = response.json()["error"]
    assert {p["path"] for p in error["problems"]} == {
        "timestamp", "clusters.0.annotations.1.confidence"}
    assert all(p["item"] == 1 for p in error["problems"])
    assert snapshot(store) == before


@pytest.mark.parametrize("body, message", [
    (b'{"timestamp": 1,', "not valid JSON"),
    (b"[]", "empty"),
    (b"\xff\xfe", "not valid JSON"),
])
def test_bodies_that_are_not_scenes(client, body, message):
    response = client.post("/api/scenes", content=body,
                           headers={"content-type": "application/json"})
    assert response.status_code == 422
    assert message in response.json()["error"]["message"]


def test_operators_in_values_are_plain_data_and_refused(client, store):
    """A MongoDB operator smuggled in a value is just a wrong type, never a query."""
    scene = valid_scene(seed=6, timestamp=STAMP + 30)
    scene["robot"] = {"$gt": ""}
    before = snapshot(store)
    response = client.post("/api/scenes", json=scene)
    assert response.status_code == 422
    assert response.json()["error"]["problems"][0]["path"] == "robot"
    assert snapshot(store) == before


def test_bodies_over_the_limit_get_413(client, store):
    big = valid_scene(seed=7, timestamp=STAMP + 40)
    big["clusters"][0]["annotations"][0]["source"] = "x" * (2 * 2**20)
    before = snapshot(store)
    response = client.post("/api/scenes", content=json.dumps(big),
                           headers={"content-type": "application/json"})
    assert response.status_code == 413
    assert "limit" in response.json()["error"]["message"]
    assert snapshot(store) == before


NDJSON = {"content-type": "application/x-ndjson"}
JSON = {"content-type": "application/json"}


def ndjson(*scenes) -> bytes:
    return b"".join(json.dumps(scene).encode() + b"\n" for scene in scenes)


def test_post_a_batch_as_ndjson(client, store):
    batch = [valid_scene(seed=i, timestamp=STAMP + 50 + i) for i in range(3)]
    body = ndjson(batch[0]) + b"\n  \n" + ndjson(*batch[1:]).replace(b"\n", b"\r\n")
    response = client.post("/api/scenes", content=body, headers=NDJSON)
    assert response.status_code == 201, response.text
    stored = response.json()["scenes"]
    assert [s["created"] for s in stored] == [True, True, True]
    assert [store.get_scene(ObjectId(s["scene_id"])).timestamp for s in stored] == [
        STAMP + 50, STAMP + 51, STAMP + 52]  # blank lines skipped, CRLF taken
    again = client.post("/api/scenes", json=batch).json()["scenes"]
    assert [s["scene_id"] for s in again] == [s["scene_id"] for s in stored]


def test_invalid_ndjson_lines_get_422_naming_scene_and_line_and_nothing_is_written(
        client, store):
    bad = valid_scene(seed=9, timestamp=STAMP + 62)
    bad["clusters"][0]["annotations"][1]["confidence"] = 7
    body = (ndjson(valid_scene(seed=8, timestamp=STAMP + 60)) + b"\n"
            + b'{"timestamp": 1,\n' + ndjson(bad, [valid_scene(seed=10, timestamp=STAMP + 63)]))
    before = snapshot(store)
    response = client.post("/api/scenes", content=body, headers=NDJSON)
    assert response.status_code == 422
    problems = {(p["item"], p["path"]): p["message"]
                for p in response.json()["error"]["problems"]}
    assert problems.keys() == {(1, ""), (2, "clusters.0.annotations.1.confidence"), (3, "")}
    assert problems[1, ""].startswith("line 3 is not valid JSON")  # (line 2 is blank)
    assert problems[3, ""] == "a scene is a JSON object, not list"
    assert snapshot(store) == before


@pytest.mark.parametrize("body", [b"", b"\n \r\n\n"])
def test_an_ndjson_body_of_no_scene_is_a_422(client, body):
    response = client.post("/api/scenes", content=body, headers=NDJSON)
    assert response.status_code == 422
    assert response.json()["error"]["message"] == "the batch is empty"


def test_ndjson_bodies_over_the_limit_get_413(client, store):
    scenes = [valid_scene(seed=11, timestamp=STAMP + 70 + i) for i in range(2)]
    scenes[1]["clusters"][0]["annotations"][0]["source"] = "x" * (2 * 2**20)
    before = snapshot(store)
    response = client.post("/api/scenes", content=ndjson(*scenes), headers=NDJSON)
    assert response.status_code == 413
    assert snapshot(store) == before


def test_another_scene_at_a_stored_robot_and_time_is_refused_not_lost(client, store):
    """The same scene again is stored once (201, created false); a different one at that robot
    and time would be acknowledged and dropped: it is a 409 naming both, and nothing of its
    batch is written."""
    first = valid_scene(seed=3, timestamp=STAMP + 70)
    assert client.post("/api/scenes", json=first).status_code == 201
    assert client.post("/api/scenes", json=first).json()["scenes"][0]["created"] is False
    clusters = store.clusters.count_documents({})
    other = valid_scene(seed=4, timestamp=STAMP + 70)
    fresh = valid_scene(seed=5, timestamp=STAMP + 71)
    answer = client.post("/api/scenes", json=[fresh, other])
    assert answer.status_code == 409
    error = answer.json()["error"]
    assert "has another scene stored at timestamp" in error["message"]
    assert f"{STAMP + 70}" in error["message"]
    assert store.clusters.count_documents({}) == clusters
    assert not store.scenes.count_documents({"timestamp": STAMP + 71})


def test_two_different_scenes_at_one_robot_and_time_in_one_body_are_refused(client, store):
    """A JSON array or NDJSON body holding two scenes of one robot and time that differ was
    answered 201 (created, then created false) and the second dropped: it is a 409, and
    nothing of the body is written (bodies the worker processes make: test_json_workers)."""
    clusters = store.clusters.count_documents({})
    first, other = valid_scene(seed=3, timestamp=STAMP + 72), valid_scene(seed=4,
                                                                          timestamp=STAMP + 72)
    for body, headers in ((json.dumps([first, other]), JSON), (ndjson(first, other), NDJSON)):
        answer = client.post("/api/scenes", content=body, headers=headers)
        assert answer.status_code == 409, answer.text
        assert "two different scenes at timestamp" in answer.json()["error"]["message"]
    assert store.clusters.count_documents({}) == clusters
    assert not store.scenes.count_documents({"timestamp": STAMP + 72})


def test_ndjson_is_taken_by_post_scenes_only(client):
    response = client.post("/api/clusters", content=b"{}\n", headers=NDJSON)
    assert response.status_code == 415
    assert "application/json" in response.json()["error"]["message"]


def test_a_configured_token_guards_writes(store):
    guarded = TestClient(create_app(store, Settings(token="s3cret")), base_url=LOCAL)
    scene = valid_scene(seed=8, timestamp=STAMP + 90)  # (a time of its own: a scene's name)
    missing = guarded.post("/api/scenes", json=scene)
    assert missing.status_code == 401
    assert missing.headers["WWW-Authenticate"].startswith("Bearer ")  # (RFC 9110: a 401 has it)
    bare = guarded.post("/api/scenes", json=scene, headers={"Authorization": "s3cret"})
    assert bare.status_code == 401 and "WWW-Authenticate" in bare.headers
    assert "send Authorization: Bearer <token>" in bare.json()["error"]["message"]
    assert "s3cret" not in bare.text
    empty = guarded.post("/api/scenes", json=scene, headers={"Authorization": "Bearer "})
    assert empty.status_code == 401 and "WWW-Authenticate" in empty.headers
    wrong = guarded.post("/api/scenes", json=scene, headers={"Authorization": "Bearer nope"})
    assert wrong.status_code == 403
    right = guarded.post("/api/scenes", json=scene, headers={"Authorization": "Bearer s3cret"})
    assert right.status_code == 201
    assert guarded.get("/api/schema/scene").status_code == 200  # reading needs no token


def test_the_api_docs_need_no_cdn_and_no_inline_script(client):
    docs = client.get("/docs")
    assert "/static/ui/swagger/swagger-ui-bundle.js" in docs.text and "cdn" not in docs.text.lower()
    assert "<script>" not in docs.text and 'data-openapi-url="/openapi.json"' in docs.text
    policy = docs.headers["content-security-policy"]
    for directive in ("default-src 'none'", "script-src 'self'", "style-src 'self'",
                      "img-src 'self' data:", "connect-src 'self'", "frame-ancestors 'none'"):
        assert f"{directive};" in f"{policy};", directive
    assert docs.headers["referrer-policy"] == "no-referrer"
    for asset in ("swagger-ui-bundle.js", "swagger-ui.css", "init.js"):
        assert client.get(f"/static/ui/swagger/{asset}").status_code == 200, asset
