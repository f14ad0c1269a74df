"""`pmem correct ...` and `pmem corrections` against a day of the kitchen week: corrections
with who made them, and every mistake one line `Error: ...` with exit 1."""

from __future__ import annotations

import json

import pytest
from bson import ObjectId
from click.testing import CliRunner

from percept_memory.cli import main
from percept_memory.demo import kitchen_week
from percept_memory.memory.schema import OBJECTS

from .conftest import ingest_consolidated


@pytest.fixture(scope="module")
def env(store, mongo_uri, db_name):
    ingest_consolidated(store, kitchen_week.generate(days=1).scenes)
    return {"MONGODB_URI": mongo_uri, "PMEM_DB": db_name}


def pmem(env, *args: str):
    return CliRunner().invoke(main, list(args), env=env)


def test_nothing_corrected_yet_says_so(env):
    result = pmem(env, "corrections")
    assert result.exit_code == 1 and result.output.strip() == "Error: no corrections"


def test_a_relabel_and_its_undo_from_the_command_line(env, store):
    cluster = store.clusters.find_one({"object_id": {"$ne": None}})
    made = pmem(env, "correct", "relabel", str(cluster["_id"]), "blue mug", "--author", "ana")
    assert made.exit_code == 0, made.output
    kind, correction, _, author = made.output.split()
    assert (kind, author) == ("relabel", "ana")
    assert store.db[OBJECTS].find_one({"_id": cluster["object_id"]})["name"] == "blue mug"
    undone = pmem(env, "correct", "undo", str(cluster["_id"]), correction, "--author", "bo")
    assert undone.exit_code == 0 and undone.output.startswith("undo ")
    listed = pmem(env, "corrections", "--json")
    rows = json.loads(listed.output)
    assert [r["kind"] for r in rows[:2]] == ["undo", "relabel"]
    assert rows[0]["time"].endswith("Z") and isinstance(rows[0]["time_ns"], int)  # README
    assert rows[1]["undone_by"]["author"] == "bo"
    text = pmem(env, "corrections", "--author", "ana").output
    assert "(undone by bo)" in text and f" ana          {rows[1]['time'][:19]}Z  cluster" in text


def test_a_split_from_the_command_line(env, store):
    obj = store.db[OBJECTS].find_one({"observations": {"$gte": 3}})
    clusters = [c["_id"] for c in store.clusters.find({"object_id": obj["_id"]}).sort(
        "search.time", -1).limit(2)]
    made = pmem(env, "correct", "split", str(obj["_id"]), *map(str, clusters),
                "--author", "ana")
    assert made.exit_code == 0, made.output
    ((kind, correction, _, author),) = [line.split() for line in made.stdout.splitlines()]
    assert (kind, author) == ("split", "ana")
    # who is who changed: said that the belief follows once a consolidator runs
    assert made.stderr.startswith("the belief of kitchen-week is rebuilt with it")
    (row,) = json.loads(pmem(env, "corrections", "--json", "--limit", "1").output)
    assert (row["kind"], row["id"], row["cluster_id"]) == ("split", correction, str(clusters[1]))
    assert sorted(row["split_off"]) == sorted(map(str, clusters))  # the earlier holds it
    listed = pmem(env, "corrections", "--limit", "1").output
    assert f"2 split off from {obj['observations'] - 2}" in listed


@pytest.mark.parametrize("args, words", [
    (["correct", "split", "OBJECT", "nope"], "clusters: 'nope' is not an id"),
    (["correct", "split", "OBJECT", "CLUSTER"], "is not an observation of object"),
    (["correct", "relabel", "nope", "mug"], "cluster: 'nope' is not an id"),
    (["correct", "relabel", str(ObjectId()), "mug"], "no cluster"),
    (["correct", "undo", "CLUSTER", str(ObjectId())], "no correction"),
    (["correct", "relabel", "CLUSTER", " "], "class_name"),
    (["correct", "merge", "CLUSTER", "CLUSTER"], "itself"),
])
def test_bad_corrections_are_one_line_and_exit_1(env, store, args, words):
    found = store.clusters.find_one({"object_id": {"$ne": None}})
    other = store.db[OBJECTS].find_one({"_id": {"$ne": found["object_id"]}})
    named = {"CLUSTER": str(found["_id"]), "OBJECT": str(other["_id"])}
    result = pmem(env, *[named.get(a, a) for a in args], "--author", "ana")
    assert result.exit_code == 1, result.output
    (line,) = result.output.strip().splitlines()
    assert line.startswith("Error: ") and words in line, line


def test_what_a_terminal_would_act_on_is_printed_as_escapes(env, store):
    """A rejection's reason is free text: an escape sequence in it cleared the screen of
    whoever listed the corrections, or wrote their clipboard (OSC 52)."""
    cluster = store.clusters.find_one({"object_id": {"$ne": None}}, sort=[("_id", -1)])
    made = pmem(env, "correct", "reject", str(cluster["_id"]), "--author", "ana", "--reason",
                "glare\x1b[2J\x1b]52;c;ZWNobyBwd25lZAo=\x07\nfake row")
    assert made.exit_code == 0, made.output
    listed = pmem(env, "corrections", "--author", "ana").output
    assert "\x1b" not in listed and "\x07" not in listed
    assert "glare\\x1b[2J\\x1b]52;c;ZWNobyBwd25lZAo=\\x07\\nfake row" in listed
    refused = pmem(env, "correct", "relabel", str(cluster["_id"]), "mug\x1b[2J", "--author",
                   "ana")
    assert refused.exit_code == 1 and "control characters" in refused.output
    assert "\x1b" not in refused.output
