"""The catalogue in MongoDB: kept by the memory pipeline, equal when rebuilt from the scenes,
and asked which objects the home has and whether an observation was seen before."""

from __future__ import annotations

import json
import re
from collections import Counter
from html import unescape

import pytest
from bson import ObjectId

from percept_memory.demo import kitchen_week
from percept_memory.ingest.service import memory_pipeline
from percept_memory.memory.pipeline import request_rebuild
from percept_memory.memory.schema import CATALOGUE, CATALOGUE_HISTORY, CATALOGUE_TRACKS
from percept_memory.queries import catalogue

from .conftest import ingest_consolidated
from .test_pipeline import canonical_belief


@pytest.fixture(scope="module")
def week(store):
    week = kitchen_week.generate(days=4)  # the fourth brings entries that merge
    ingest_consolidated(store, week.scenes)
    truth = {cluster.id: week.truth.object_at(i, j)
             for i, scene in enumerate(week.scenes) for j, cluster in enumerate(scene.clusters)}
    return week, truth


def stored_catalogue(store) -> tuple[list, list, list]:
    """The models, tracks and merges and splits, object ids aside (a rebuild makes them
    afresh; models are named by the stored clusters' ids)."""
    models = [{k: v for k, v in doc.items() if k != "object_id"}
              for doc in store.db[CATALOGUE].find().sort("_id")]
    tracks = sorted(({k: v for k, v in doc.items() if k != "_id"}
                     for doc in store.db[CATALOGUE_TRACKS].find()), key=lambda d: d["model"])
    history = [{k: v for k, v in doc.items() if k != "_id"}
               for doc in store.db[CATALOGUE_HISTORY].find().sort("_id")]
    return models, tracks, history


def test_the_catalogue_rebuilt_from_the_scenes_equals_the_one_built_live(store, week):
    """And so does the belief, whose objects identity merged where the catalogue learnt them
    as one (the rebuild consolidates in batches of another size)."""
    live = stored_catalogue(store), canonical_belief(store)
    assert live[0][0] and live[0][1] and live[0][2]
    request_rebuild(store)
    rebuild = memory_pipeline(store)
    rebuild.batch = 7
    rebuild.drain(timeout=600)
    assert (stored_catalogue(store), canonical_belief(store)) == live


def test_the_home_s_objects_are_entries_of_one_kind_of_object_each(store, week):
    """Two cups of one set look the same: an entry is what an object looks like, so it may hold
    both (identity keeps them apart by where they are), but never a cup and a plate."""
    _, truth = week
    found = catalogue.entries(store, limit=1000)
    assert found and found == sorted(found, key=lambda e: (-e["times_seen"], e["entry"]))
    mixed = []
    for entry in found:
        real = Counter(truth[view].split("#")[0] for view in map(_object_id, entry["views"]))
        if len(real) > 1:
            mixed.append((entry["names"], real))
        assert entry["now"] is not None and entry["names"] and entry["times_seen"] >= 1
    assert not mixed
    assert len({e["entry"] for e in found}) == len(found)


def test_an_object_in_several_entries_is_not_counted_whole_in_each(store, week):
    """The demo's plates: one belief object's models in three entries made each entry say it
    was seen as often as the object (1,111 sightings for 982 clusters); its sightings are
    shared among them now."""
    found = catalogue.entries(store, limit=1000)
    seen = {doc["_id"]: doc["seen"] for doc in store.db["catalogue_tracks"].find()}
    assert sum(e["times_seen"] for e in found) <= sum(seen.values())
    # one plate seen 126 times, its models in three entries (5, 1 and 1 of its 7)
    plate, entries = ObjectId(), [ObjectId() for _ in range(3)]
    models = [(entries[0], 5), (entries[1], 1), (entries[2], 1)]
    try:
        store.db["objects"].insert_one({"_id": plate, "map": "plates", "name": "plate"})
        store.db["catalogue_tracks"].insert_one({"_id": plate, "map": "plates", "seen": 126})
        store.db["catalogue"].insert_many([
            {"map": "plates", "object_id": plate, "elements": [], "length": 10, "edges": [],
             "entry": entry} for entry, n in models for _ in range(n)])
        shown = {e["entry"]: e["times_seen"] for e in catalogue.entries(store, "plates")}
        assert shown == {str(entries[0]): 90, str(entries[1]): 18, str(entries[2]): 18}
        alone = catalogue.entries(store, "plates", only=[entries[1]])  # (seen-before's)
        assert [e["times_seen"] for e in alone] == [18]
    finally:
        for name in ("objects", "catalogue_tracks", "catalogue"):
            store.db[name].delete_many({"map": "plates"})


def test_an_observation_is_recognised_as_the_entry_holding_its_views(store, week):
    _, truth = week
    found = catalogue.entries(store, limit=1000)
    entry = next(e for e in found if e["models"] > 1) if any(
        e["models"] > 1 for e in found) else found[0]
    view = _object_id(entry["views"][0])
    ranked = catalogue.seen_before(store, view)
    assert ranked[0]["entry"] == entry["entry"] and ranked[0]["inclusion"] == 1.0
    assert ranked == sorted(ranked, key=lambda e: -e["inclusion"])
    assert all(0 <= e["consensus"] <= 1 for e in ranked)


def test_the_entries_are_the_connected_components_of_the_similarity_graph(store, week):
    graph = catalogue.similarity_graph(store, "kitchen-week")
    entry_of = {m["model"]: m["entry"] for m in graph["models"]}
    assert graph["links"] and all(entry_of[link["a"]] == entry_of[link["b"]]
                                  for link in graph["links"])
    neighbours: dict = {}
    for link in graph["links"]:
        neighbours.setdefault(link["a"], set()).add(link["b"])
        neighbours.setdefault(link["b"], set()).add(link["a"])
    for model, entry in entry_of.items():  # reached from the model naming its entry
        seen, todo = {entry}, [entry]
        while todo:
            for other in neighbours.get(todo.pop(), ()):
                if other not in seen:
                    seen.add(other)
                    todo.append(other)
        assert model in seen
    assert {e["entry"]: e["models"] for e in catalogue.entries(store, limit=1000)} == dict(
        Counter(entry_of.values()))


def kinds_of_objects(store, truth: dict) -> dict:
    """Belief object -> the kinds of item its observations show (cup, plate, ...)."""
    kinds: dict = {}
    for doc in store.clusters.find({"object_id": {"$ne": None}}, {"object_id": 1}):
        kinds.setdefault(doc["object_id"], set()).add(truth[doc["_id"]].split("#")[0])
    return kinds


def test_what_the_catalogue_learns_as_one_object_the_belief_holds_as_one(store, week,
                                                                          mongo_uri):
    """An item that came back after a while elsewhere showing a side identity had not linked
    to it is a new object to identity alone; the catalogue learns its two tracks as one entry,
    and identity then merges them (consolidation.py `_recalled`), history and all: fewer
    objects than identity alone keeps, none of two kinds of item, every observation still an
    event of its object."""
    from pymongo import MongoClient

    from percept_memory.memory.consolidation import Consolidation
    from percept_memory.memory.pipeline import Pipeline
    from percept_memory.memory.settings import Settings
    from percept_memory.memory.store import CLIENT_OPTIONS, MemoryStore

    scenes, truth = week
    with MongoClient(mongo_uri, **CLIENT_OPTIONS) as client:
        alone = MemoryStore(client, f"{store.db.name}_alone",
                            gridfs_threshold=Settings().gridfs_threshold)
        try:
            alone.prepare()
            alone.put_scenes(scenes.scenes)
            Pipeline(alone, [Consolidation(alone)]).drain(timeout=600)
            without = alone.db["objects"].count_documents({})
        finally:
            client.drop_database(alone.db.name)
    kinds = kinds_of_objects(store, truth)
    assert len(kinds) == store.db["objects"].count_documents({})
    assert len(kinds) <= without - 2
    assert not [k for k in kinds.values() if len(k) > 1]
    observed = store.clusters.count_documents({"object_id": {"$ne": None}})
    assert store.db["events"].count_documents({"cluster_id": {"$ne": None}}) == observed
    # the joined tracks' first sightings are moves of the older objects now, with the likeness
    recalled = list(store.db["events"].find({"explanation": "move", "alternatives": {
        "$size": 1}, "alternatives.0.object_id": None, "alternatives.0.explanation": "appear"}))
    assert len(recalled) >= without - len(kinds)
    assert all(0 < e["probability"] <= 1 for e in recalled)
    # and the catalogue's models and tracks of a merged object are those of the object kept
    objects = set(kinds)
    assert set(store.db[CATALOGUE].distinct("object_id")) <= objects
    assert set(store.db[CATALOGUE_TRACKS].distinct("_id")) <= objects


def test_seen_before_an_unknown_cluster_is_not_found(store):
    from bson import ObjectId

    from percept_memory.memory.errors import NotFound

    with pytest.raises(NotFound):
        catalogue.seen_before(store, ObjectId())


def _object_id(text: str):
    from bson import ObjectId

    return ObjectId(text)


def test_the_api_and_the_cli_answer_the_same(store, week, mongo_uri, db_name):
    from click.testing import CliRunner
    from fastapi.testclient import TestClient

    from percept_memory import answers
    from percept_memory.cli import main
    from percept_memory.memory.settings import Settings
    from percept_memory.webui.app import create_app

    from .conftest import LOCAL

    client = TestClient(create_app(store, Settings()), base_url=LOCAL)
    listed = client.get("/api/catalogue", params={"limit": 3})
    assert listed.status_code == 200
    assert listed.json()["entries"] == catalogue.entries(store, limit=3)
    every = catalogue.entries(store, limit=1000)
    assert listed.json()["total"] == len(every) > 6
    rest = client.get("/api/catalogue", params={"limit": 1000, "offset": 3}).json()["entries"]
    assert [e["entry"] for e in listed.json()["entries"] + rest] == [e["entry"] for e in every]
    # the page showed the 100 most seen of 389 with no word of the rest: its pages reach all
    shown, url = [], "/catalogue?limit=3"
    while url:
        html = client.get(url).text
        assert f" of {len(every)}." in html
        shown += re.findall(r'<tr id="entry-([0-9a-f]{24})">', html)
        url = (found := re.search(r'<a href="([^"]+)" rel="next">', html)) and unescape(found[1])
    assert shown == [str(e["entry"]) for e in every]
    past = client.get(f"/catalogue?offset={len(every) + 50}").text
    assert f"No entries after the first {len(every)}." in past and "rel=\"prev\"" in past
    view = listed.json()["entries"][0]["views"][0]
    ranked = client.get(f"/api/catalogue/seen-before/{view}").json()["entries"]
    assert ranked == catalogue.seen_before(store, _object_id(view))
    graph = client.get("/api/catalogue/graph", params={"map": "kitchen-week"})
    assert graph.json() == catalogue.similarity_graph(store, "kitchen-week")
    for entry in listed.json()["entries"]:  # its own models and the links between them
        models = {m["model"] for m in entry["graph"]["models"]}
        assert len(models) == entry["models"] and set(entry["views"]) <= models
        assert all({link["a"], link["b"]} <= models for link in entry["graph"]["links"])
    changes = client.get("/api/catalogue/history", params={"map": "kitchen-week"}).json()
    assert changes["changes"] == catalogue.history(store, "kitchen-week")
    assert changes["changes"], "four days of the kitchen merge or split some entries"
    times = [c["time"] for c in changes["changes"]]
    assert times == sorted(times, reverse=True)
    for change in changes["changes"]:
        shape = (len(change["before"]), len(change["after"]))
        assert shape[0] > 1 and shape[1] == 1 if change["kind"] == "merged" else (
            shape[0] == 1 and shape[1] > 1)
        assert set(change["current"]) <= set(change["after"])
    for bad, status in (("/api/catalogue/graph", 422),
                        ("/api/catalogue/seen-before/nothex", 422),
                        (f"/api/catalogue/seen-before/{'0' * 24}", 404),
                        ("/api/catalogue?limit=0", 422),
                        ("/api/catalogue/history?limit=0", 422)):
        answer = client.get(bad)
        assert answer.status_code == status and "message" in answer.json()["error"]

    env = {"MONGODB_URI": mongo_uri, "PMEM_DB": db_name}
    shown = CliRunner().invoke(main, ["query", "catalogue", "--limit", "3", "--json"], env=env)
    assert shown.exit_code == 0, shown.output
    entries = json.loads(shown.stdout)
    assert entries == answers.plain(listed.json()["entries"])  # (moments as ISO 8601 + ns)
    assert entries[0]["now"]["last_seen"].endswith("Z") and entries[0]["now"]["last_seen_ns"]
    total = listed.json()["total"]
    assert shown.stderr.strip() == f"entries 1-3 of {total}"
    rest = CliRunner().invoke(main, ["query", "catalogue", "--offset", "3", "--limit", "1000",
                                     "--json"], env=env)
    assert [e["entry"] for e in entries + json.loads(rest.stdout)] == [
        str(e["entry"]) for e in catalogue.entries(store, limit=1000)]
    past = CliRunner().invoke(main, ["query", "catalogue", "--offset", str(total)], env=env)
    assert past.exit_code == 1
    assert past.output.strip() == f"Error: no entries after the first {total}"
    text = CliRunner().invoke(main, ["query", "seen-before", view], env=env)
    assert text.exit_code == 0 and text.stdout.startswith("inclusion 1.00")
    for args in (["query", "seen-before", "nothex"], ["query", "seen-before", "0" * 24],
                 ["query", "catalogue", "--map", "nowhere"]):
        failed = CliRunner().invoke(main, args, env=env)
        assert failed.exit_code == 1 and failed.output.startswith("Error: "), failed.output
