"""Search by meaning (queries/meaning.py): the words a text means, found offline from the word
vectors in wordllama's wheel and ranked after the words it spells, over the engine, the API,
the CLI and the search page, on three generated kitchen days."""

from __future__ import annotations

import asyncio
import json
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest
from bson import ObjectId
from click.testing import CliRunner
from fastapi.testclient import TestClient
from playwright.sync_api import expect
from pymongo import AsyncMongoClient

from percept_memory.cli import main
from percept_memory.demo import kitchen_week
from percept_memory.memory.async_store import AsyncMemoryStore
from percept_memory.memory.settings import Settings
from percept_memory.memory.store import CLIENT_OPTIONS
from percept_memory.memory.types import Classification, Cluster, Scene
from percept_memory.queries import meaning
from percept_memory.queries.engine import AsyncQueryEngine, QueryEngine
from percept_memory.webui.app import create_app

from .conftest import LOCAL, ingest_consolidated, served
from .test_webui import browser, page, shot  # noqa: F401 (fixtures)

DRINKS = {"water", "juice", "milk", "tea"}


@pytest.fixture(scope="module")
def item(store) -> dict[ObjectId, str]:
    """Three kitchen days (the chocolate first appears on the third), consolidated: cluster id
    -> the catalogue item it shows."""
    week = kitchen_week.generate(days=3)
    ingest_consolidated(store, week.scenes)
    return {cluster.id: kitchen_week.item_of(week.truth.object_at(i, j)).key
            for i, scene in enumerate(week.scenes) for j, cluster in enumerate(scene.clusters)}


def test_the_word_vectors_load_from_the_wheel_alone(tmp_path):
    """In a process that can open no connection, with an empty home: nothing is fetched."""
    script = textwrap.dedent("""
        import json, socket
        def refused(*args, **kwargs):
            raise OSError("no network in this test")
        socket.socket.connect = socket.create_connection = refused
        from percept_memory.queries.meaning import VECTORS
        v = VECTORS.embed(["something to drink", "beverage", "screwdriver"])
        print(json.dumps([float(v[0] @ v[1]), float(v[0] @ v[2])]))
    """)
    env = {**os.environ, "HOME": str(tmp_path), "HF_HUB_OFFLINE": "1",
           "XDG_CACHE_HOME": str(tmp_path / "cache")}
    done = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True,
                          text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    drink, tool = json.loads(done.stdout)
    assert drink > 0.4 > tool
    assert not any(tmp_path.iterdir()), "something was written to the home directory"


def test_word_vectors_are_kept_and_score_as_fresh_ones(monkeypatch):
    vectors = meaning.WordVectors()
    monkeypatch.setattr(meaning, "MAX_CACHED", 4)
    first = vectors.similarities(["milk", "water"], "a drink")
    words = ["water", "tea", "milk", "tea"]  # one word new, one twice
    fresh = vectors.embed(words) @ vectors.embed(["a drink"])[0]
    again = vectors.similarities(words, "a drink")
    assert np.allclose(again, fresh, atol=1e-6) and again[2] == first[0]
    more = ["knife", "fork", "spoon", "plate"]  # over the bound: only these are kept
    assert np.allclose(vectors.similarities(more, "cutlery"),
                       vectors.embed(more) @ vectors.embed(["cutlery"])[0], atol=1e-6)
    assert np.allclose(vectors.similarities(words, "a drink"), fresh, atol=1e-6)


def test_something_to_drink_finds_the_drinks_only_by_meaning(store, item):
    engine = QueryEngine(store)
    assert engine.clusters(text="something to drink").items == []
    found = engine.clusters(text="something to drink", meaning=True, limit=10).items
    assert len(found) == 10 and {item[h.id] for h in found} <= DRINKS
    assert "water" in {item[h.id] for h in found}
    scores = [h.score for h in found]
    assert scores == sorted(scores, reverse=True) and 0 < scores[-1] < 1


def test_the_meaning_is_of_the_words_alone(store, item):
    """The text's words mean it: quotes, punctuation and case do not change what it finds."""
    engine = QueryEngine(store)
    plain = engine.clusters(text="something to drink", meaning=True, limit=5)
    odd = engine.clusters(text='"Something" to DRINK?!', meaning=True, limit=5)
    assert odd.items == plain.items


def test_the_async_engine_means_the_same(store, item, mongo_uri):
    async def ask():
        client = AsyncMongoClient(mongo_uri, **CLIENT_OPTIONS)
        try:
            engine = AsyncQueryEngine(AsyncMemoryStore(client, store.db.name,
                                                       gridfs_threshold=1024))
            return await engine.clusters(text="something to drink", meaning=True, limit=20)
        finally:
            await client.close()

    assert asyncio.run(ask()) == QueryEngine(store).clusters(text="something to drink",
                                                             meaning=True, limit=20)


def test_something_sweet_finds_the_chocolate(store, item):
    found = QueryEngine(store).clusters(text="something sweet", meaning=True).items
    assert found and {item[h.id] for h in found} == {"milka"}


def test_words_spelt_rank_before_words_meant(store, item):
    """"milk" finds the milk by its word, then what means the same (the carton says dairy)."""
    found = [item[h.id] for h in QueryEngine(store).clusters(
        text="milk", meaning=True, limit=500).items]
    milk = sum(key == "milk" for key in item.values())
    assert found[:milk] == ["milk"] * milk and len(found) > milk


@pytest.fixture(scope="module")
def settings(tmp_path_factory, mongo_uri, db_name) -> Settings:
    return Settings(mongodb_uri=mongo_uri, db=db_name,
                    data_dir=tmp_path_factory.mktemp("data"), consolidator=False)


@pytest.fixture(scope="module")
def client(store, item, settings):
    return TestClient(create_app(store, settings), base_url=LOCAL)


def test_the_api_searches_by_meaning(client, item):
    answer = client.get("/api/clusters", params={"text": "something to drink",
                                                 "meaning": "true", "limit": 5})
    assert answer.status_code == 200, answer.text
    hits = answer.json()["items"]
    assert len(hits) == 5 and {item[ObjectId(h["id"])] for h in hits} <= DRINKS
    posted = client.post("/api/clusters", json={"text": "something to drink", "meaning": True,
                                                "limit": 5})
    assert posted.status_code == 200 and posted.json()["items"] == hits


@pytest.mark.parametrize(("params", "words"), [
    ({"meaning": "true"}, "meaning needs text"),
    ({"text": "drink", "meaning": "perhaps"}, "meaning"),
    ({"text": "drink", "meaning": ["true", "false"]}, "meaning"),
])
def test_bad_meaning_requests_get_the_json_error_shape(client, params, words):
    answer = client.get("/api/clusters", params=params)
    assert answer.status_code == 422, answer.text
    error = answer.json()["error"]
    assert words in error["message"] + json.dumps(error["problems"])


def test_pmem_query_clusters_by_meaning(settings, item, mongo_uri, db_name):
    env = {"MONGODB_URI": mongo_uri, "PMEM_DB": db_name, "PMEM_DATA_DIR": str(settings.data_dir)}
    found = CliRunner().invoke(main, ["query", "clusters", "--text", "something to drink",
                                      "--meaning", "--limit", "3", "--json"], env=env)
    assert found.exit_code == 0, found.output
    assert {item[ObjectId(h["id"])] for h in json.loads(found.stdout)["items"]} <= DRINKS
    bad = CliRunner().invoke(main, ["query", "clusters", "--meaning"], env=env)
    assert bad.exit_code == 1 and bad.stderr.startswith("Error:")
    assert "meaning needs text" in bad.stderr


@pytest.fixture(scope="module")
def url(store, item, settings):
    with served(create_app(store, settings)) as url:
        yield url


def test_the_search_box_understands_meaning(page, url, item):  # noqa: F811 (page: a fixture)
    page.goto(f"{url}/search")
    page.get_by_role("searchbox", name="Text").fill("something to drink")
    page.get_by_role("button", name="Search").click()
    expect(page.locator("p.summary")).to_contain_text("0 shown")
    page.get_by_label("by meaning").check()
    page.get_by_role("button", name="Search").click()
    expect(page).to_have_url(f"{url}/search?text=something+to+drink&meaning=true&view=grid")
    expect(page.get_by_label("by meaning")).to_be_checked()
    hits = page.locator("ul.results li.hit")
    expect(hits.first).to_be_visible()
    found = [ObjectId(i) for i in hits.evaluate_all("els => els.map(e => e.dataset.cluster)")]
    assert {item[i] for i in found[:10]} <= DRINKS
    scores = [float(s) for s in hits.locator(".score").all_inner_texts()]
    assert len(scores) == len(found) and scores == sorted(scores, reverse=True)
    page.goto(f"{url}/search?text=something+to+drink&meaning=true&limit=8")
    shot(page, "search-meaning")


def test_a_word_stored_after_a_query_is_meant_by_the_next(store, item):
    """The vocabulary a process keeps is read again once it grew (last: it adds a cluster)."""
    engine = QueryEngine(store)
    before = engine.clusters(text="lemon", meaning=True, limit=500).items
    (stored,) = store.put_scenes([Scene(timestamp=1, robot="probe", clusters=[Cluster(
        annotations=[Classification(class_name="lemonade", source="test")])])])
    after = engine.clusters(text="lemon", meaning=True, limit=500).items
    assert stored.cluster_ids[0] in {h.id for h in after} - {h.id for h in before}
