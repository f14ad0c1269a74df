"""What the app survives beyond malformed scenes (test_malformed.py): positions as far as a
float goes (in queries, exports and pages), a database that does not answer, the image limits'
settings, documents over MongoDB's limit, an empty queue."""

from __future__ import annotations

import io
import time
import zipfile

import cv2
import pytest
from fastapi.testclient import TestClient
from pymongo import MongoClient

from percept_memory.memory.settings import Settings
from percept_memory.memory.store import CLIENT_OPTIONS, MemoryStore
from percept_memory.memory.types import Scene
from percept_memory.memory.types.base import MAX_TIMESTAMP
from percept_memory.webui.app import create_app

from .conftest import LOCAL, ingest_consolidated
from .test_ingest import STAMP, valid_scene
from .test_malformed import CROP, b64, counts, png, spoilt
from .test_mongod import free_port

FAR = 1e308


@pytest.fixture(scope="module")
def client(store):
    return TestClient(create_app(store, Settings(consolidator=False)), base_url=LOCAL)


@pytest.fixture(scope="module")
def far_cluster(client) -> str:
    scene = valid_scene(seed=3, timestamp=STAMP + 3)
    scene["clusters"][0]["annotations"][0]["position"] = [FAR, -FAR, 0.0]
    response = client.post("/api/scenes", json=scene)
    assert response.status_code == 201, response.text
    return response.json()["scenes"][0]["cluster_ids"][0]


@pytest.mark.parametrize("query", [{"sphere": f"0,0,0,{FAR}"},
                                   {"box": f"{-FAR},{-FAR},{-FAR},{FAR},{FAR},{FAR}"},
                                   {"near": f"{FAR},0,0"}, {"near": "0,0,0", "k": 1000}])
def test_volumes_and_points_as_far_as_floats_go_find_the_far_cluster(client, far_cluster,
                                                                    query):
    response = client.get("/api/clusters", params={**query, "limit": 500})
    assert response.status_code == 200, response.text
    assert far_cluster in [item["id"] for item in response.json()["items"]]


@pytest.mark.parametrize("path, extra", [("/api/clusters", {}), ("/api/stats/annotations", {}),
                                         ("/api/what-is-at", {}), ("/api/changes", {"t1": 0}),
                                         ("/api/export", {"format": "jsonl"})])
def test_a_sphere_reaching_past_the_largest_float_is_answered(client, far_cluster, path,
                                                              extra):
    sphere = {"center": [FAR, 0, -FAR], "radius": FAR}
    assert client.post(path, json={"sphere": sphere, **extra}).status_code == 200
    assert client.get(path, params={"sphere": f"{FAR},0,{-FAR},{FAR}", **extra}
                      ).status_code == 200


def test_an_export_of_everything_holds_the_far_cluster(client, far_cluster):
    response = client.post("/api/export", json={
        "format": "jsonl", "sphere": {"center": [0, 0, 0], "radius": FAR}})
    assert response.status_code == 200, response.text
    with zipfile.ZipFile(io.BytesIO(response.content)) as archive:
        assert far_cluster in archive.read("features.jsonl").decode()


def test_the_enrichment_page_shows_an_empty_queue(client):
    assert client.get("/enrichment").status_code == 200


@pytest.mark.parametrize("limit, value", [("max_image_pixels", 1000),
                                          ("max_crop_pixels", 63 * 64)])
def test_the_image_limits_are_settings(store, limit, value):
    """The scene's crops are 64 x 64: refused under these limits, taken under the defaults."""
    strict = TestClient(create_app(store, Settings(consolidator=False, **{limit: value})),
                        base_url=LOCAL)
    response = strict.post("/api/scenes", json=spoilt(f"{CROP}.png", png(64, 64)))
    assert response.status_code == 422
    assert f"64 x 64 pixels, over the limit of {value}" in response.text


def test_without_a_database_reads_and_writes_get_a_prompt_503():
    client = MongoClient(f"mongodb://127.0.0.1:{free_port()}/?directConnection=true",
                         serverSelectionTimeoutMS=500, **CLIENT_OPTIONS)
    unreachable = MemoryStore(client, "nowhere", gridfs_threshold=2**17)
    app = TestClient(create_app(unreachable, Settings(consolidator=False)), base_url=LOCAL)
    for method, path, body in [("GET", "/api/clusters?text=cereal", None),
                               ("POST", "/api/clusters", {"text": "cereal"}),
                               ("POST", "/api/scenes", valid_scene(seed=4)),
                               ("GET", "/api/pipeline", None)]:
        started = time.monotonic()
        response = app.request(method, path, json=body)
        assert response.status_code == 503, response.text
        assert response.json()["error"]["status"] == 503
        assert time.monotonic() - started < 5
    client.close()


def test_an_export_limit_beyond_64_bits_is_refused_by_name(client):
    response = client.get("/api/export", params={"format": "jsonl", "limit": 2**64})
    assert response.status_code == 422
    assert response.json()["error"]["problems"][0]["path"] == "limit"


def test_a_cluster_over_mongodbs_document_limit_gets_413_and_stores_nothing(client, store):
    scene = valid_scene(seed=5, timestamp=STAMP + 5)
    scene["clusters"][0]["annotations"] += [
        {"_type": "pm.annotation.Text", "source": "OCR", "text": "y" * 1_000_000}] * 17
    before = counts(store)
    response = client.post("/api/scenes", json=scene)
    assert response.status_code == 413
    assert "16 MB limit" in response.json()["error"]["message"]
    assert counts(store) == before


def test_the_map_and_object_pages_draw_positions_as_far_apart_as_floats_go(client, store):
    scenes = []
    for i, position in enumerate([[FAR, -FAR, 0.0], [-FAR, FAR, FAR]]):
        scene = valid_scene(seed=6, timestamp=STAMP + 60 + i)
        scene["map"] = "far"
        scene["clusters"][0]["annotations"][0]["position"] = position
        scenes.append(Scene.model_validate(scene))
    ingest_consolidated(store, scenes)
    object_id = store.clusters.find_one({"_id": scenes[0].clusters[0].id})["object_id"]
    assert client.get("/map", params={"map": "far"}).status_code == 200
    assert client.get(f"/objects/{object_id}").status_code == 200


def test_the_last_timestamp_of_the_range_is_shown_on_every_page(client, store):
    """2262-04-11T23:47:16Z: pages round times up to whole seconds, and this one still fits
    int64 nanoseconds (one nanosecond later is refused: test_malformed.py)."""
    scene = valid_scene(seed=7, timestamp=MAX_TIMESTAMP)
    scene["map"] = "late"
    validated = Scene.model_validate(scene)
    ingest_consolidated(store, [validated])
    object_id = store.clusters.find_one({"_id": validated.clusters[0].id})["object_id"]
    for path in ("/map?map=late", f"/objects/{object_id}", f"/scenes/{validated.id}",
                 "/scenes", "/api/what-is-at?map=late&region=counter_top_island"):
        assert client.get(path).status_code == 200, path


def test_the_scene_log_and_search_stay_up_when_the_names_stored_pass_16_mb(client, store):
    """Names are capped now, but data stored before or by other means may hold any: the
    forms' lists of names (one `distinct` answer, at most 16 MB) failed every page for good."""
    big = [{"timestamp": i, "robot": f"hostile{i}", "map": "hostile", "clusters": [],
            "summary": {"regions": [f"{i:02d}" + "r" * 2**20], "annotators": [], "types": []}}
           for i in range(17)]
    inserted = store.scenes.insert_many(big).inserted_ids
    store.clusters.insert_many([{"scene_id": None, "search": {
        "region": doc["summary"]["regions"][0], "robot": "pr2", "time": 1}} for doc in big])
    try:
        for path in ("/?robot=nobody", "/search?text=cup"):
            answer = client.get(path)
            assert answer.status_code == 200, path
            assert len(answer.content) < 2**20, path
    finally:
        store.scenes.delete_many({"_id": {"$in": inserted}})
        store.clusters.delete_many({"scene_id": None})


def test_an_image_s_name_is_one_segment_of_its_url_whatever_it_holds(client, kitchen_rgb):
    """An image named ../../../../api/export?format=coco made every viewer's browser ask for
    an export; one named depth/../color showed another image."""
    import re
    from html import unescape

    names = ["../../../../api/export?format=coco", "depth/../color", "a?b#c d", "rgb.png"]
    scene = valid_scene(seed=12, timestamp=STAMP + 12)
    small = cv2.imencode(".png", kitchen_rgb[::8, ::8])[1].tobytes()
    scene["images"] = {name: {"encoding": "bgr8", "png": b64(small)} for name in names}
    (stored,) = client.post("/api/scenes", json=scene).json()["scenes"]
    page = client.get(f"/scenes/{stored['scene_id']}").text
    sources = [unescape(s) for s in re.findall(r'<img src="(/img/scenes/[^"]+/images/[^"]+)"',
                                               page)]
    assert len(sources) == len(names)
    for source in sources:
        assert "/../" not in source and "?" not in source and "#" not in source
        answer = client.get(source)
        assert answer.status_code == 200 and answer.headers["content-type"] == "image/png", (
            source, answer.text[:200])


def test_a_page_shows_the_start_of_a_text_of_a_mib(client):
    """A log line's or an OCR text's MiB (as much as a text may hold) was copied whole into
    each page that shows it: the scene page grew to 17 MB."""
    scene = valid_scene(seed=13, timestamp=STAMP + 13)
    scene["log"] = [{"_type": "pm.annotation.LogLine", "source": "OCR", "level": "warning",
                     "message": "w" * 2**20}]
    scene["clusters"][0]["annotations"].append({"_type": "pm.annotation.Text", "source": "OCR",
                                                "text": "t" * 2**20})
    (stored,) = client.post("/api/scenes", json=scene).json()["scenes"]
    for path in (f"/scenes/{stored['scene_id']}", f"/clusters/{stored['cluster_ids'][0]}",
                 "/annotators"):
        page = client.get(path)
        assert page.status_code == 200 and len(page.content) < 2**18, (path, len(page.content))
    assert "more characters)" in client.get(f"/scenes/{stored['scene_id']}").text
