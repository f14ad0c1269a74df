"""Corrections over HTTP (webui/curation.py) and in a real headless Chromium, by keyboard: the
API's writes need the token and JSON from this site, bad input gets the one error shape; the
cluster, object and audit pages correct, show and undo."""

from __future__ import annotations

from contextlib import contextmanager

import pytest
from bson import ObjectId
from fastapi.testclient import TestClient
from playwright.sync_api import expect, sync_playwright

from percept_memory.demo import kitchen_week
from percept_memory.ingest.service import memory_pipeline
from percept_memory.memory import curation
from percept_memory.memory.schema import EVENTS, MAPS, OBJECTS
from percept_memory.memory.settings import Settings
from percept_memory.memory.types import Classification, GroundTruth
from percept_memory.webui import curation as curation_page
from percept_memory.webui import render
from percept_memory.webui.app import create_app

from .conftest import LOCAL, ingest_consolidated, served
from .test_webui import CHROMIUM, SCREENSHOTS

JSON = {"content-type": "application/json"}


@pytest.fixture(scope="module")
def memory(store):
    ingest_consolidated(store, kitchen_week.generate(days=1).scenes)
    return store


@pytest.fixture(scope="module")
def client(memory):
    return TestClient(create_app(memory, Settings(consolidator=False)), base_url=LOCAL)


def clusters_of_objects(store, count: int, skip: int = 0) -> list:
    """Clusters of distinct objects no one corrected yet."""
    found, seen = [], set()
    for doc in store.clusters.find({"object_id": {"$ne": None},
                                    "annotations.author": {"$exists": False}},
                                   {"object_id": 1}).sort("_id", 1).skip(skip):
        if doc["object_id"] not in seen:
            seen.add(doc["object_id"])
            found.append(doc)
        if len(found) == count:
            return found
    raise AssertionError("not enough objects")


def test_a_relabel_over_http_names_the_object_and_is_audited(client, memory):
    (doc,) = clusters_of_objects(memory, 1)
    answer = client.post(f"/api/clusters/{doc['_id']}/relabel", headers=JSON,
                         json={"label": "blue mug", "author": "ana"})
    assert answer.status_code == 201, answer.text
    made = answer.json()["correction"]
    assert made["_type"] == "pm.annotation.Relabel" and made["author"] == "ana"
    assert memory.db[OBJECTS].find_one({"_id": doc["object_id"]})["name"] == "blue mug"
    audit = client.get("/api/corrections").json()
    assert audit["corrections"][0]["id"] == made["_id"]
    assert audit["corrections"][0]["cluster_id"] == str(doc["_id"])
    assert audit["counts"]["relabel"] >= 1
    undone = client.post(f"/api/clusters/{doc['_id']}/corrections/{made['_id']}/undo",
                         headers=JSON, json={"author": "bo"})
    assert undone.status_code == 201 and undone.json()["correction"]["undoes"] == made["_id"]
    assert memory.db[OBJECTS].find_one({"_id": doc["object_id"]})["name"] != "blue mug"
    again = client.post(f"/api/clusters/{doc['_id']}/corrections/{made['_id']}/undo",
                        headers=JSON, json={"author": "bo"})
    assert again.status_code == 422 and "in force" in again.json()["error"]["message"] + str(
        again.json()["error"]["problems"])


def test_an_object_is_relabelled_through_its_latest_observation(client, memory):
    (doc,) = clusters_of_objects(memory, 1, skip=40)
    believed = memory.db[OBJECTS].find_one({"_id": doc["object_id"]})
    answer = client.post(f"/api/objects/{believed['_id']}/relabel", headers=JSON,
                         json={"label": "kettle", "author": "ana"})
    assert answer.status_code == 201
    assert memory.db[OBJECTS].find_one({"_id": believed["_id"]})["name"] == "kettle"
    assert curation.audit(memory, 1)[0]["cluster_id"] == believed["last_cluster"]


def error_of(answer, status: int) -> dict:
    assert answer.status_code == status, answer.text
    body = answer.json()
    assert set(body) == {"error"} and body["error"]["status"] == status
    return body["error"]


@pytest.mark.parametrize("body, path", [
    ({"label": "", "author": "ana"}, "body.label"),
    ({"label": "mug", "author": "  "}, "body.author"),
    ({"label": "mug"}, "body.author"),
    ({"author": "ana"}, "body.label"),
    ({"label": ["mug"], "author": "ana"}, "body.label"),
    ({"label": "mug", "author": "ana", "time": 5}, "body.time"),  # not ours to set: refused
])
def test_a_bad_relabel_is_a_422_naming_the_field_and_writes_nothing(client, memory, body, path):
    (doc,) = clusters_of_objects(memory, 1, skip=60)
    before = memory.clusters.find_one({"_id": doc["_id"]})["annotations"]
    error = error_of(client.post(f"/api/clusters/{doc['_id']}/relabel", headers=JSON,
                                 json=body), 422)
    assert path in [p["path"] for p in error["problems"]]
    assert memory.clusters.find_one({"_id": doc["_id"]})["annotations"] == before


def test_a_misspelt_field_of_a_correction_is_refused_not_dropped(client, memory):
    (doc,) = clusters_of_objects(memory, 1, skip=61)
    error = error_of(client.post(f"/api/clusters/{doc['_id']}/reject", headers=JSON,
                                 json={"author": "ana", "reson": "a reflection"}), 422)
    assert "body.reson" in [p["path"] for p in error["problems"]]
    assert not memory.clusters.find_one({"_id": doc["_id"], "annotations.author": "ana"})


def test_unknown_and_malformed_ids_are_refused_not_crashed_on(client):
    error_of(client.post(f"/api/clusters/{ObjectId()}/relabel", headers=JSON,
                         json={"label": "mug", "author": "ana"}), 404)
    error_of(client.post(f"/api/objects/{ObjectId()}/relabel", headers=JSON,
                         json={"label": "mug", "author": "ana"}), 404)
    error_of(client.post("/api/clusters/nope/reject", headers=JSON, json={"author": "ana"}), 422)
    error_of(client.post("/api/clusters/nope/relabel", headers=JSON, content=b"{"), 422)


def test_writes_are_json_from_this_site_only_and_need_the_token(memory):
    (doc,) = clusters_of_objects(memory, 1, skip=80)
    path = f"/api/clusters/{doc['_id']}/reject"
    guarded = TestClient(create_app(memory, Settings(token="s3cret", consolidator=False)),
                         base_url=LOCAL)
    error_of(guarded.post(path, data={"author": "ana"}), 415)  # what a plain form sends
    error_of(guarded.post(path, headers={**JSON, "origin": "https://evil.example"},
                          json={"author": "ana"}), 403)
    error_of(guarded.post(path, headers=JSON, json={"author": "ana"}), 401)
    error_of(guarded.post(path, headers={**JSON, "authorization": "Bearer nope"},
                          json={"author": "ana"}), 403)
    assert not memory.clusters.find_one({"_id": doc["_id"], "annotations.author": "ana"})
    answer = guarded.post(path, headers={**JSON, "authorization": "Bearer s3cret"},
                          json={"author": "ana", "reason": "a reflection"})
    assert answer.status_code == 201


def test_corrections_are_in_the_openapi_description(client):
    paths = client.get("/openapi.json").json()["paths"]
    for path in ("/api/clusters/{cluster_id}/relabel", "/api/clusters/{cluster_id}/reject",
                 "/api/clusters/{cluster_id}/corrections/{correction_id}/undo",
                 "/api/objects/{object_id}/relabel", "/api/clusters/{cluster_id}/merge",
                 "/api/objects/{object_id}/merge", "/api/objects/{object_id}/split"):
        assert {"401", "403", "415", "422"} <= set(paths[path]["post"]["responses"])
    assert "/api/corrections" in paths


# --- in Chromium, by keyboard ---------------------------------------------------------------


def launch(playwright):
    return playwright.chromium.launch(executable_path=str(CHROMIUM), args=[
        "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking"])


def watched(browser):
    tab = browser.new_page(viewport={"width": 1280, "height": 900})
    blocked: list[str] = []
    tab.on("console", lambda m: blocked.append(m.text) if "Content Security" in m.text
           else None)
    return tab, blocked


@contextmanager
def in_chromium(memory, settings: Settings | None = None):
    """The app served on the memory and a Chromium tab for it: (tab, url). Its pages must keep
    their own Content-Security-Policy."""
    app = create_app(memory, settings or Settings())  # (its consolidator: as deployed)
    with served(app) as url, sync_playwright() as playwright:
        browser = launch(playwright)
        tab, blocked = watched(browser)
        yield tab, url
        browser.close()
    assert not blocked, f"the page broke its own Content-Security-Policy: {blocked}"


def test_a_cluster_is_relabelled_rejected_and_undone_by_keyboard(memory):
    (doc,) = clusters_of_objects(memory, 1, skip=100)
    with in_chromium(memory) as (tab, url):
        tab.goto(f"{url}/clusters/{doc['_id']}")
        tab.locator("#author").focus()
        tab.keyboard.type("ana")
        tab.keyboard.press("Tab")  # the label field of the relabel form
        tab.keyboard.type("green teapot")
        with tab.expect_navigation():
            tab.keyboard.press("Enter")
        verdict = tab.locator("p.verdict")
        expect(verdict).to_contain_text("A person says this is green teapot")
        expect(tab.locator("#author")).to_have_value("ana")  # remembered
        object_id = memory.clusters.find_one({"_id": doc["_id"]})["object_id"]
        assert memory.db[OBJECTS].find_one({"_id": object_id})["name"] == "green teapot"
        tab.get_by_role("button", name="This detection is wrong").focus()
        with tab.expect_navigation():
            tab.keyboard.press("Enter")
        expect(verdict).to_contain_text("detection is wrong")
        SCREENSHOTS.mkdir(parents=True, exist_ok=True)
        tab.locator("section.curation").screenshot(path=str(SCREENSHOTS / "correct.png"))
        tab.get_by_role("button", name="Undo rejection").focus()
        with tab.expect_navigation():
            tab.keyboard.press("Enter")
        expect(verdict).to_contain_text("green teapot")

        tab.goto(f"{url}/corrections")
        rows = tab.locator("table.audit tbody tr")
        expect(rows.first).to_contain_text("undo of")
        expect(rows.nth(1)).to_contain_text("by ana")  # the rejection, undone by ana
        tab.screenshot(path=str(SCREENSHOTS / "corrections.png"), full_page=False)


def test_with_a_token_the_page_asks_for_it_once(memory):
    (doc,) = clusters_of_objects(memory, 1, skip=120)
    with in_chromium(memory, Settings(token="s3cret", consolidator=False)) as (tab, url):
        tab.goto(f"{url}/objects/{doc['object_id']}")
        tab.locator("#author").fill("ana")
        tab.locator("form.relabel input[name=label]").focus()
        tab.keyboard.type("fruit bowl")
        tab.keyboard.press("Enter")
        token = tab.locator("#token")
        expect(token).to_be_focused()
        expect(tab.locator("form.relabel [role=status]")).to_contain_text("write token")
        tab.keyboard.type("s3cret")
        with tab.expect_navigation():
            tab.keyboard.press("Enter")
        expect(tab.locator("h1")).to_contain_text("fruit bowl")


def test_a_cluster_with_a_ground_truth_shows_it_beside_the_predictions(client, memory):
    (doc,) = clusters_of_objects(memory, 1, skip=140)
    memory.add_annotation(doc["_id"], GroundTruth(source="PnP09", class_name="Teapot"))
    cluster = memory.get_cluster(doc["_id"])
    (predicted, *_) = cluster.annotations_of(Classification)
    curation.relabel(memory, doc["_id"], "teapot", author="ana")
    rows = curation_page.versus_truth(memory.get_cluster(doc["_id"]))
    assert {"source": "ana", "name": "teapot", "confidence": None,
            "kind": "pm.annotation.Relabel", "true": True} in rows
    mine = [r for r in rows if r["source"] == predicted.source
            and r["name"] == predicted.class_name]
    assert mine and mine[0]["true"] is False  # (the kitchen week has no teapot)
    text = client.get(f"/clusters/{doc['_id']}").text
    assert '<strong class="truth">Teapot</strong>' in text
    assert '<tr class="right"><td>ana</td><td>teapot</td>' in text
    assert curation_page.versus_truth(memory.get_cluster(
        clusters_of_objects(memory, 1, skip=150)[0]["_id"])) == []


def test_two_objects_are_merged_over_http_and_a_bad_merge_is_refused(client, memory):
    first, *others = memory.db[OBJECTS].find().sort("_id", 1).skip(10)
    scene_of = {c["_id"]: c["scene_id"] for c in memory.clusters.find({}, {"scene_id": 1})}
    second = next(o for o in others
                  if scene_of[o["last_cluster"]] != scene_of[first["last_cluster"]])
    error_of(client.post(f"/api/objects/{first['_id']}/merge", headers=JSON,
                         json={"other": str(ObjectId()), "author": "ana"}), 404)
    error = error_of(client.post(f"/api/clusters/{first['last_cluster']}/merge", headers=JSON,
                                 json={"other": str(first["last_cluster"]), "author": "ana"}),
                     422)
    assert error["problems"][0]["path"] == "body.other"
    answer = client.post(f"/api/objects/{first['_id']}/merge", headers=JSON,
                         json={"other": str(second["_id"]), "author": "ana"})
    assert answer.status_code == 201
    made = answer.json()["correction"]
    assert made["_type"] == "pm.annotation.SameObject"
    assert {made["other"]} < {str(first["last_cluster"]), str(second["last_cluster"])}
    assert client.get("/api/corrections?limit=1").json()["corrections"][0]["kind"] == "merge"


def test_an_object_is_merged_from_its_page_by_keyboard(memory):
    cluster = memory.clusters.find_one({"annotations.author": {"$exists": False},
                                        "object_id": {"$ne": None}}, sort=[("_id", -1)])
    this = memory.db[OBJECTS].find_one({"_id": cluster["object_id"]})
    this_last, cluster_count = this["last_cluster"], this["observations"]
    with in_chromium(memory) as (tab, url):
        tab.goto(f"{url}/objects/{cluster['object_id']}")
        tab.locator("#author").fill("ana")
        choice = tab.locator("form.merge select[name=other]")
        choice.focus()
        tab.keyboard.press("ArrowDown")
        other = choice.input_value()
        other_last = memory.db[OBJECTS].find_one({"_id": ObjectId(other)})["last_cluster"]
        tab.keyboard.press("Tab")  # to Merge
        with tab.expect_navigation(timeout=60_000):
            tab.keyboard.press("Enter")
        # reloaded once the map's belief was rebuilt with it: the object as merged (it
        # reloaded at once, showing the object as it was, with no word of the rebuild)
        shown = int(tab.locator("dd.observations").text_content())
        expect(tab.locator("p.note", has_text="being rebuilt")).to_have_count(0)
        now = memory.db[OBJECTS].find_one({"_id": ObjectId(tab.url.rsplit("/", 1)[1])})
        assert shown == now["observations"] and now["observations"] > cluster_count
    (row,) = curation.audit(memory, 1)
    assert row["kind"] == "merge" and row["author"] == "ana"
    assert {row["cluster_id"], row["other"]} == {other_last, this_last}


def test_objects_seen_beside_one_are_not_offered_to_merge_it_with(memory):
    """Such a merge is refused (two observations of one scene are two objects): offered, a
    person's choice met a 422."""
    for believed in memory.db[OBJECTS].find({"observations": {"$gte": 3}}):
        history = list(memory.db[EVENTS].find({"object_id": believed["_id"]}))
        offered = {o["_id"] for o in curation_page.merge_candidates(memory, believed, history)}
        scenes = {e["scene_id"] for e in history if e.get("cluster_id")}
        beside = set(memory.db[EVENTS].distinct("object_id", {
            "scene_id": {"$in": list(scenes)}, "cluster_id": {"$ne": None}}))
        assert not offered & beside, believed["name"]


def test_a_corrections_time_shows_as_a_time_on_the_cluster_page(client, memory):
    (doc,) = clusters_of_objects(memory, 1, skip=60)
    made = curation.relabel(memory, doc["_id"], "blue mug", author="ana")
    text = client.get(f"/clusters/{doc['_id']}").text
    assert str(made.time) not in text  # (its nanoseconds since 1970, before)
    assert f"<td>{render.time_of(made.time)}</td>" in text


def test_an_object_page_says_when_its_maps_belief_is_being_rebuilt(client, memory):
    believed = memory.db[OBJECTS].find_one()
    assert "being rebuilt" not in client.get(f"/objects/{believed['_id']}").text
    maps = memory.db[MAPS]
    maps.update_one({"_id": believed["map"]}, {"$set": {"catch_up": [1, ObjectId()]}})
    try:
        assert f"map {believed['map']} is being rebuilt" in client.get(
            f"/objects/{believed['_id']}").text
    finally:
        maps.update_one({"_id": believed["map"]}, {"$set": {"catch_up": None}})


def often_seen(store, skip: int = 0) -> dict:
    """An object seen in several scenes, none of its clusters corrected."""
    for obj in store.db[OBJECTS].find({"observations": {"$gte": 4}}).sort("_id", -1).skip(skip):
        if not store.clusters.find_one({"object_id": obj["_id"],
                                        "annotations.author": {"$exists": True}}):
            return obj
    raise AssertionError("no object seen often enough")


def test_an_object_is_split_over_http_and_a_bad_split_is_refused(client, memory):
    obj = often_seen(memory, skip=3)
    theirs = [c["_id"] for c in memory.clusters.find({"object_id": obj["_id"]}).sort(
        "search.time", 1)]
    stranger = memory.clusters.find_one({"object_id": {"$nin": [obj["_id"], None]}})["_id"]
    path = f"/api/objects/{obj['_id']}/split"
    for body, field in [({"clusters": [], "author": "ana"}, "body.clusters"),
                        ({"clusters": [str(stranger)], "author": "ana"}, "body.clusters"),
                        ({"clusters": ["nope"], "author": "ana"}, "body.clusters.0"),
                        ({"clusters": [str(theirs[-1])], "author": ""}, "body.author")]:
        error = error_of(client.post(path, headers=JSON, json=body), 422)
        assert field in [p["path"] for p in error["problems"]], error
    error_of(client.post(f"/api/objects/{ObjectId()}/split", headers=JSON,
                         json={"clusters": [str(theirs[-1])], "author": "ana"}), 404)
    assert not memory.clusters.find_one({"object_id": obj["_id"],
                                         "annotations.author": {"$exists": True}})
    body = {"clusters": [str(c) for c in theirs[1::2]], "author": "ana"}
    guarded = TestClient(create_app(memory, Settings(token="s3cret", consolidator=False)),
                         base_url=LOCAL)
    error_of(guarded.post(path, data=body), 415)  # what a plain form sends
    error_of(guarded.post(path, headers={**JSON, "origin": "https://evil.example"}, json=body),
             403)
    error_of(guarded.post(path, headers=JSON, json=body), 401)
    assert not memory.clusters.find_one({"object_id": obj["_id"],
                                         "annotations.author": {"$exists": True}})
    answer = guarded.post(path, headers={**JSON, "authorization": "Bearer s3cret"}, json=body)
    assert answer.status_code == 201, answer.text
    made = answer.json()["correction"]
    assert made["_type"] == "pm.annotation.DifferentObject"
    assert made["split_off"] == body["clusters"]
    assert made["apart_from"] == [str(c) for c in theirs[::2]]
    (row,) = client.get("/api/corrections?limit=1").json()["corrections"]
    assert (row["kind"], row["id"], row["cluster_id"]) == ("split", made["_id"], str(theirs[1]))
    split, kept = len(made["split_off"]), len(made["apart_from"])
    assert f"split of {split} observations from {kept}" in client.get(
        f"/clusters/{theirs[1]}").text  # with its Undo
    assert f"{split} observations split off as another object, apart from {kept} others" in (
        client.get("/corrections").text)


def test_a_split_of_the_older_kind_is_listed_not_crashed_on(client, memory):
    """(Before splits named both sides, one kept its cluster apart from one other.)"""
    holder, other = (c["_id"] for c in clusters_of_objects(memory, 2, skip=60))
    memory.clusters.update_one({"_id": holder}, {"$push": {"annotations": {
        "_type": "pm.annotation.DifferentObject", "_id": ObjectId(), "source": "human",
        "author": "old", "time": 1, "apart_from": other}}})
    (row,) = client.get("/api/corrections?author=old").json()["corrections"]
    assert (row["split_off"], row["apart_from"]) == ([str(holder)], [str(other)])
    page = client.get("/corrections?author=old")
    assert "1 observations split off as another object, apart from 1 others" in page.text


def test_an_object_is_split_from_its_page_by_keyboard_and_the_split_is_audited(memory):
    obj = often_seen(memory)
    with in_chromium(memory) as (tab, url):
        tab.goto(f"{url}/objects/{obj['_id']}")
        tab.locator("#author").fill("ana")
        boxes = tab.locator("form.split input[name=clusters]")
        boxes.first.focus()  # the newest observations come first
        tab.keyboard.press("Space")
        tab.keyboard.press("Tab")
        tab.keyboard.press("Space")
        ticked = [boxes.nth(i).get_attribute("value") for i in range(2)]
        tab.keyboard.press("Tab")  # past the other observations to the button
        while tab.evaluate("document.activeElement.type") == "checkbox":
            tab.keyboard.press("Tab")
        expect(tab.get_by_role("button", name="Split off as another object")).to_be_focused()
        SCREENSHOTS.mkdir(parents=True, exist_ok=True)
        tab.locator("form.split").screenshot(path=str(SCREENSHOTS / "split.png"))
        with tab.expect_navigation():
            tab.keyboard.press("Enter")
        memory_pipeline(memory).drain(timeout=300)
        tab.goto(f"{url}/corrections")
        expect(tab.locator("table.audit tbody tr").first).to_contain_text(
            "2 observations split off as another object")
    (row,) = curation.audit(memory, 1)
    assert (row["kind"], row["author"]) == ("split", "ana")
    assert sorted(row["split_off"]) == sorted(map(ObjectId, ticked))
    assert len(row["apart_from"]) == obj["observations"] - 2
    def objects(ids):
        return {memory.clusters.find_one({"_id": c})["object_id"] for c in ids}
    assert not objects(row["split_off"]) & objects(row["apart_from"])


def test_object_ids_outlive_a_rebuild_and_a_merged_ones_address_leads_to_its_object(client,
                                                                                    memory):
    """An object is named by its first observation, so a rebuild (every reject, merge or
    split asks for one) gives the objects it does not change their ids again, and the page
    of an object merged into another leads to that one."""
    named = {o["_id"] for o in memory.db[OBJECTS].find({}, {"_id": 1})}
    assert all(memory.clusters.find_one({"_id": key}) for key in named)
    first, *others = memory.db[OBJECTS].find().sort("_id", 1)
    scene_of = {c["_id"]: c["scene_id"] for c in memory.clusters.find({}, {"scene_id": 1})}
    second = next(o for o in others
                  if scene_of[o["last_cluster"]] != scene_of[first["last_cluster"]])
    curation.merge(memory, first["last_cluster"], second["last_cluster"], author="ana")
    memory_pipeline(memory).drain(timeout=300)
    now = {o["_id"] for o in memory.db[OBJECTS].find({}, {"_id": 1})}
    (gone,) = named - now
    assert now < named  # all but the one merged away kept their ids
    kept = memory.clusters.find_one({"_id": gone})["object_id"]
    answer = client.get(f"/objects/{gone}", follow_redirects=False)
    assert answer.status_code == 303 and answer.headers["location"] == f"/objects/{kept}"
    assert client.get(f"/objects/{ObjectId()}").status_code == 404
