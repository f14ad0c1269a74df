"""The query API over HTTP and `pmem query`: both forms of every endpoint, one error format,
limits, a server-side time limit, and no way for a user value to become a MongoDB operator."""

from __future__ import annotations

import json
import re
from datetime import UTC, datetime

import pytest
from click.testing import CliRunner
from fastapi.testclient import TestClient
from pymongo import MongoClient, monitoring

from percept_memory.cli import main
from percept_memory.memory.settings import Settings
from percept_memory.memory.store import CLIENT_OPTIONS, MemoryStore
from percept_memory.queries.engine import QUERIES, QueryEngine
from percept_memory.webui.app import create_app
from percept_memory.webui.html import nanoseconds
from percept_memory.webui.queries import PATHS

from .conftest import LOCAL

# a valid query of every endpoint, as query-string pairs
VALID = {
    "clusters": {"text": "Prinles", "region": "shelf", "limit": "3"},
    "where_is": {"x": "ketchup"},
    "where_was": {"x": "fairy"},
    "last_seen": {"x": "milk"},
    "what_is_at": {"region": "table", "t": "2024-03-06T08:30"},
    "changes": {"region": "table", "t1": "2024-03-06T07:00", "t2": "2024-03-06T10:00"},
    "annotation_stats": {"region": "shelf"},
    "cooccurrence": {"x": "nutella"},
    "timings": {"robot": "pr2"},
    "playback": {"robot": "pr2", "t": "2024-03-06T08:30", "step": "next"},
    "annotator_report": {"scenes": "50", "robot": "pr2"},
    "annotator_clusters": {"robot": "pr2", "annotator": "SVMClassifier",
                           "reference": "(ground truth)", "said": "cereal"},
}
assert set(VALID) == set(QUERIES)


def path(name: str) -> str:
    return "/api/" + PATHS.get(name, name.replace("_", "-"))


@pytest.fixture(scope="module")
def client(store, kitchen):
    return TestClient(create_app(store, Settings()), base_url=LOCAL)


@pytest.mark.parametrize("name", VALID)
def test_query_string_and_json_body_give_the_same_answer(client, name):
    by_get = client.get(path(name), params=VALID[name])
    body = {k: ([v] if k == "region" and name == "clusters" else v) for k, v in VALID[name].items()}
    by_post = client.post(path(name), json=body)
    assert by_get.status_code == by_post.status_code == 200, (by_get.text, by_post.text)
    assert by_get.json() == by_post.json() and by_get.json()


def test_pages_follow_the_cursor(client):
    first = client.get("/api/clusters", params={"region": "table", "limit": 5}).json()
    second = client.get("/api/clusters", params={"region": "table", "limit": 5,
                                                 "cursor": first["next"]}).json()
    both = [h["id"] for h in first["items"] + second["items"]]
    everything = client.post("/api/clusters", json={"region": ["table"], "limit": 10}).json()
    assert both == [h["id"] for h in everything["items"]] and len(set(both)) == 10


def test_the_openapi_description_lists_every_query(client):
    paths = client.get("/openapi.json").json()["paths"]
    for name in QUERIES:
        assert {"get", "post"} <= set(paths[path(name)])
    names = {p["name"] for p in paths["/api/clusters"]["get"]["parameters"]}
    assert {"text", "region", "box", "sphere", "near", "where", "cursor"} <= names


SMUGGLED_JSON = [{"$where": "sleep(1000)"}, {"$gt": ""}, {"$ne": None}, [{"$gt": ""}],
                 {"$function": {"body": "return 1", "args": [], "lang": "js"}}]


@pytest.mark.parametrize("name", VALID)
@pytest.mark.parametrize("operator", SMUGGLED_JSON, ids=str)
def test_operators_smuggled_through_json_are_refused(client, store, name, operator):
    for field in VALID[name]:
        body = {**VALID[name], field: operator}
        response = client.post(path(name), json=body)
        assert response.status_code == 422, (field, response.text)
        assert set(response.json()) == {"error"} and response.json()["error"]["problems"]
    response = client.post(path(name), json={**VALID[name], "$where": "1"})
    assert response.status_code == 422


@pytest.mark.parametrize("name", VALID)
def test_operators_in_query_strings_are_plain_data_or_refused(client, name):
    bracketed = client.get(f"{path(name)}?{next(iter(VALID[name]))}[$gt]=")
    assert bracketed.status_code == 422
    for field in VALID[name]:
        response = client.get(path(name), params={**VALID[name], field: "$where"})
        assert response.status_code in (200, 404, 422), response.text
        if response.status_code == 200:  # taken as the text "$where", which matches nothing
            assert "$where" not in json.dumps(response.json())


def test_operator_text_is_data_matching_nothing(client):
    as_list = client.post("/api/clusters", json={"region": ["$where"], "robot": ["$ne"]})
    assert as_list.status_code == 200 and as_list.json()["items"] == []
    for params in ({"region": "$where"}, {"robot": '{"$ne": null}'}, {"text": "$where"},
                   {"where": 'shape:shape={"$ne": null}'}):
        response = client.get("/api/clusters", params=params)
        assert response.status_code == 200 and response.json()["items"] == [], params
    refused = client.get("/api/clusters", params={"where": "shape:$where=1"})
    assert refused.status_code == 422 and "$" in refused.json()["error"]["problems"][0]["message"]


@pytest.mark.parametrize("params, problem", [
    ({"limit": "501"}, "limit"), ({"near": "0,0,0", "k": "5000"}, "k"),
    ({"region": [f"r{i}" for i in range(40)]}, "region"),
    ({"where": [f"shape:shape=s{i}" for i in range(20)]}, "where"),
    ({"text": " ".join(f"w{i}" for i in range(30))}, ""),
    ({"text": "x" * 600}, "text"), ({"box": "1,1,1,0,0,0"}, "box"), ({"limit": "2", "k": "1"}, ""),
    ({"after": "yesterday"}, "after"), ({"near": "0,0,0", "sort": "newest"}, ""),
    ({"region": "table", "bogus": "1"}, "bogus"), ({"limit": ["1", "2"]}, "limit"),
])
def test_limits_and_bad_parameters_get_422_naming_them(client, params, problem):
    response = client.get("/api/clusters", params=params)
    if params.get("limit") == "2" and "k" in params:
        assert response.status_code == 200  # k without near is harmless
        return
    assert response.status_code == 422, response.text
    assert problem in {p["path"] for p in response.json()["error"]["problems"]}


def test_unknown_objects_are_404_and_query_errors_422(client):
    missing = client.get("/api/where-is", params={"x": "0" * 24})
    assert missing.status_code == 404 and "0" * 24 in missing.json()["error"]["message"]
    other = client.get("/api/clusters", params={"cursor": "bm90IGEgY3Vyc29y"})
    assert other.status_code == 422 and "cursor" in other.json()["error"]["message"]
    big = client.post("/api/clusters", content=b"{" + b" " * 70_000 + b"}",
                      headers={"content-type": "application/json"})
    assert big.status_code == 413
    # a window whose ends are reversed, on every question that takes one (some answered [])
    for path, params in (("/api/stats/cooccurrence", {}), ("/api/stats/timings", {}),
                         ("/api/where-was", {"x": "ketchup"}), ("/api/clusters", {})):
        reversed_ = client.get(path, params={**params, "after": "2024-03-07",
                                             "before": "2024-03-05"})
        assert reversed_.status_code == 422 and "later than" in reversed_.text, path
    future = client.get("/api/changes", params={"region": "table", "t1": "2200-01-01"})
    assert future.status_code == 422 and "later than now" in future.text
    beyond = client.get("/api/changes", params={"region": "table", "t1": "2999-01-01"})
    assert beyond.status_code == 422 and "to 2262-04-11" in beyond.text
    nowhere = client.get("/api/what-is-at", params={"region": "Table"})
    assert nowhere.status_code == 404 and "'table'" in nowhere.json()["error"]["message"]


class _Commands(monitoring.CommandListener):
    def __init__(self):
        self.commands: list = []

    def started(self, event):
        self.commands.append(event.command)

    def succeeded(self, event):
        pass

    def failed(self, event):
        pass


def test_every_database_command_carries_the_time_limit(mongo_uri, store, kitchen):
    listener = _Commands()
    client = MongoClient(mongo_uri, event_listeners=[listener], **CLIENT_OPTIONS)
    engine = QueryEngine(MemoryStore(client, store.db.name, gridfs_threshold=1024),
                         Settings(query_timeout_ms=1234))
    for name, query in VALID.items():
        getattr(engine, name)(**query)
    commands = [c for c in listener.commands if {"find", "aggregate", "count"} & set(c)]
    assert len(commands) > 20 and all(c.get("maxTimeMS") == 1234 for c in commands)
    client.close()


def test_pmem_query_answers_on_the_command_line(mongo_uri, db_name, kitchen):
    env = {"MONGODB_URI": mongo_uri, "PMEM_DB": db_name}
    run = CliRunner().invoke
    where = run(main, ["query", "where-is", "Heinz", "--limit", "1", "--json"], env=env)
    assert where.exit_code == 0, where.output
    (heinz,) = json.loads(where.stdout)
    assert heinz["region"] == "shelf"
    assert heinz["last_seen"] == datetime.fromtimestamp(
        heinz["last_seen_ns"] / 1e9, UTC).strftime("%Y-%m-%dT%H:%M:%S.") + \
        f"{heinz['last_seen_ns'] % 10**9:09d}Z"
    hits = run(main, ["query", "clusters", "--text", "Prinles", "--region", "shelf",
                      "--where", "classification:confidence>0.5", "--count", "--json"], env=env)
    assert hits.exit_code == 0 and json.loads(hits.stdout)["total"] > 0
    at = run(main, ["query", "what-is-at", "--region", "table", "--t", "2024-03-06T08:30",
                    "--json"], env=env)
    assert at.exit_code == 0 and json.loads(at.stdout)["objects"]
    bad = run(main, ["query", "clusters", "--limit", "9999"], env=env)
    assert bad.exit_code == 1 and "limit" in bad.output


def test_a_time_printed_to_the_nanosecond_is_read_back_to_the_nanosecond(
        client, mongo_uri, db_name, kitchen):
    env = {"MONGODB_URI": mongo_uri, "PMEM_DB": db_name}
    run = CliRunner().invoke
    where = run(main, ["query", "where-is", "Heinz", "--limit", "1", "--json"], env=env)
    (heinz,) = json.loads(where.stdout)
    seen, seen_ns = heinz["last_seen"], heinz["last_seen_ns"]
    assert seen_ns % 1000  # (a datetime would keep its microseconds only)
    at = run(main, ["query", "what-is-at", "--region", "shelf", "--t", seen, "--json"], env=env)
    assert json.loads(at.stdout)["t_ns"] == seen_ns
    answer = client.get(path("what-is-at"), params={"region": "shelf", "t": seen})
    assert answer.json()["t"] == seen_ns
    assert nanoseconds(seen, "t") == seen_ns  # the pages' reading of a time


def test_a_utc_offset_sent_unencoded_is_named_and_a_lowercase_z_is_utc(client):
    """A + in a query string arrives as a space ("08:30 01:00"): the 422 says to write %2B."""
    spaced = client.get(path("what-is-at") + "?region=shelf&t=2024-03-06T08:30+01:00")
    assert spaced.status_code == 422 and "write it %2B" in spaced.text
    encoded = client.get(path("what-is-at") + "?region=shelf&t=2024-03-06T08:30%2B01:00")
    lower = client.get(path("what-is-at"), params={"region": "shelf", "t": "2024-03-06T07:30z"})
    assert encoded.json()["t"] == lower.json()["t"] == 1709710200 * 10**9


def test_a_question_about_now_says_null_for_its_time_not_int64s_top(client):
    now = client.get(path("what-is-at"), params={"region": "shelf"}).json()
    assert now["t"] is None and now["objects"]
    changes = client.get(path("changes"), params={"region": "shelf", "t1": "2024-03-06"}).json()
    assert changes["t2"] is None and changes["t1"] == 1709683200 * 10**9
    nobody = client.get(path("playback"), params={"robot": "nobody"})
    assert nobody.status_code == 404 and "at or before now" in nobody.text
    assert str(2**63 - 1) not in nobody.text + str(now) + str(changes)


def test_pmem_query_takes_the_subject_as_argument_and_where_and_when_as_options(
        mongo_uri, db_name, kitchen):
    env = {"MONGODB_URI": mongo_uri, "PMEM_DB": db_name}
    run = CliRunner().invoke
    where = run(main, ["query", "where-is", "Heinz", "--limit", "1"], env=env)
    assert where.exit_code == 0, where.output
    header, row = where.stdout.splitlines()
    assert header.split()[:4] == ["name", "state", "map", "region"]
    assert re.search(r"\bshelf\b.* 2024-03-\d\dT\d\d:\d\d:\d\dZ ", row)
    by_hour = run(main, ["query", "cooccurrence", "Heinz", "--by-hour"], env=env)
    assert by_hour.exit_code == 0, by_hour.output
    assert by_hour.stdout.startswith("rows:\n  name ") and " shelf " in by_hour.stdout
    now = run(main, ["query", "what-is-at", "--region", "shelf"], env=env)
    assert now.exit_code == 0 and now.stdout.startswith("t: now\n")
    now = run(main, ["query", "changes", "--region", "shelf", "--t1", "2024-03-06", "--json"],
                     env=env)
    assert json.loads(now.stdout)["t2"] == "now" and str(2**63 - 1) not in now.stdout
    missing = run(main, ["query", "changes", "--region", "shelf"], env=env)
    assert missing.exit_code == 1 and "--t1" in missing.output
    nothing = run(main, ["query", "where-is", "zzyzx"], env=env)
    assert nothing.exit_code == 0 and nothing.stdout == "" and "nothing matches" in nothing.output
    # a history: each object a block, its row and its stays' table with their times
    was = run(main, ["query", "where-was", "Heinz", "--limit", "1"], env=env)
    assert was.exit_code == 0, was.output
    lines = was.stdout.splitlines()
    assert lines[0] == "object:" and lines[1].split()[:2] == ["name", "state"]
    assert lines[3] == "places:" and lines[4].split()[:4] == ["region", "position", "since",
                                                               "last_seen"]
    assert "until" in lines[4] and re.search(r"shelf .* 2024-03-\d\dT\d\d:\d\d:\d\dZ", lines[5])
    changes = run(main, ["query", "changes", "--region", "table", "--t1", "2024-03-06T08:00",
                         "--t2", "2024-03-06T12:00"], env=env)
    assert changes.exit_code == 0 and "..." not in changes.stdout  # places shown whole
