"""Annotation types of one's own in the processes pmem starts (PMEM_TYPES): the server, its
ingest worker processes and the CLI know the class, so its labels are worked out as it is
stored; a module that cannot be imported is one line naming it."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
import urllib.error
import urllib.request
from functools import cache

import pytest
from pymongo import MongoClient

from percept_memory.converters import Unknown
from percept_memory.ingest.json_batches import PARALLEL_BYTES
from percept_memory.memory.store import CLIENT_OPTIONS, MemoryStore
from percept_memory.memory.types import Cluster, Scene

from .test_json_workers import body_of
from .test_readme import free_port, wait_until_serving

MODULE = textwrap.dedent('''
    from percept_memory.memory.types import Annotation, stored_type

    @stored_type("lab.annotation.Heft")
    class Heft(Annotation):
        grams: float

        def labels(self) -> list[str]:
            return ["heavy"] if self.grams > 1000 else ["light"]
''')


def pmem_env(mongo_uri: str, db: str, folder, **more: str) -> dict:
    return {**os.environ, "MONGODB_URI": mongo_uri, "PMEM_DB": db, "PYTHONPATH": str(folder),
            "PMEM_TYPES": "heft_types", **more}


def with_heft(scenes: list[dict], grams: float) -> list[dict]:
    """Each scene's first cluster weighed."""
    for scene in scenes:
        scene["clusters"][0]["annotations"].append(
            {"_type": "lab.annotation.Heft", "source": "Scale", "grams": grams})
    return scenes


def post(url: str, body: bytes) -> dict:
    request = urllib.request.Request(url, body, {"Content-Type": "application/json"})
    with urllib.request.urlopen(request, timeout=120) as answer:
        return json.load(answer)


def pmem(env: dict, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "percept_memory", *args], env=env,
                          capture_output=True, text=True, timeout=120)


def test_the_server_its_workers_and_the_cli_know_the_types_pmem_types_names(
        mongo_uri, tmp_path, kitchen_rgb):
    (tmp_path / "heft_types.py").write_text(MODULE)
    db = "pmem_test_type_modules"
    env = pmem_env(mongo_uri, db, tmp_path, PMEM_INGEST_PROCESSES="2",
                   PMEM_CONSOLIDATOR="false")
    port = free_port()
    server = subprocess.Popen([sys.executable, "-m", "percept_memory", "serve", "--port",
                               str(port)], env=env, stderr=subprocess.PIPE, text=True)
    try:
        base = f"http://127.0.0.1:{port}"
        wait_until_serving(f"{base}/api/schema/scene")
        small = with_heft(body_of(kitchen_rgb, 0, 1), 1500)  # stored by the server itself
        large = with_heft(body_of(kitchen_rgb, 1, 24), 200)  # by its worker processes
        assert len(json.dumps(large).encode()) >= PARALLEL_BYTES
        post(f"{base}/api/scenes", json.dumps(small).encode())
        post(f"{base}/api/scenes", json.dumps(large).encode())
        for label, count in (("heavy", 1), ("light", 24)):
            with urllib.request.urlopen(
                    f"{base}/api/clusters?labelled={label}&count=true&limit=0") as answer:
                found = json.load(answer)
                assert found["total"] == count, (label, found)
    finally:
        server.terminate()
        server.wait(timeout=30)
    assert "Traceback" not in server.stderr.read()
    try:  # the CLI: `pmem reindex` works the labels out again, from the class
        MongoClient(mongo_uri)[db]["clusters"].update_many({}, {"$set": {"search.labels": []}})
        # and ones stored by a process that knew no such type: one does not fit it, one
        # lacks its field, one is heavy in a form only JSON takes (a string for a number)
        heft = {"_type": "lab.annotation.Heft", "source": "Scale"}
        stored_before = [{**heft, "grams": "a lot"}, heft, {**heft, "grams": "1500"}]
        store = MemoryStore(MongoClient(mongo_uri, **CLIENT_OPTIONS), db, gridfs_threshold=2048)
        ids = store.put_scene(Scene(timestamp=1, robot="scale", clusters=[
            Cluster(annotations=[Unknown(type_name=heft["_type"], fields=fields)])
            for fields in stored_before]))
        done = pmem(env, "reindex")
        assert done.returncode == 0 and "Traceback" not in done.stderr, done.stderr
        assert ("Warning: 2 annotation(s) do not fit their type, such as cluster "
                f"{ids.cluster_ids[0]}: lab.annotation.Heft: grams: Input should be a valid "
                "number") in done.stderr
        kept = store.clusters.find_one({"_id": ids.cluster_ids[0]})["annotations"][0]
        assert {k: kept[k] for k in stored_before[0]} == stored_before[0]  # as stored
        found = pmem(env, "query", "clusters", "--labelled", "heavy", "--count", "--limit", "0",
                     "--json")
        assert json.loads(found.stdout)["total"] == 2  # (the one posted, the one now read)
    finally:
        MongoClient(mongo_uri).drop_database(db)


@pytest.mark.parametrize("types, words", [
    ("no_such_module", "PMEM_TYPES: cannot import 'no_such_module': ModuleNotFoundError"),
    ("broken_types", "PMEM_TYPES: cannot import 'broken_types': ZeroDivisionError"),
    ("lab types", "PMEM_TYPES: 'lab types' is not a Python module name"),
    ("exiting_types", "PMEM_TYPES: cannot import 'exiting_types': SystemExit: 3"),
])
def test_a_module_that_cannot_be_imported_is_one_line(mongo_uri, tmp_path, types, words):
    (tmp_path / "broken_types.py").write_text("1 / 0\n")
    (tmp_path / "exiting_types.py").write_text("import sys\nsys.exit(3)\n")
    done = pmem(pmem_env(mongo_uri, "pmem_test_type_modules_bad", tmp_path, PMEM_TYPES=types),
                "info")
    assert done.returncode == 1 and "Traceback" not in done.stderr
    (line,) = done.stderr.splitlines()
    assert line.startswith("Error: ") and words in line


def test_the_database_s_commands_and_help_need_no_annotation_types(mongo_uri, tmp_path):
    """A module that cannot be imported stopped every command: `pmem db stop` and help too."""
    env = pmem_env(mongo_uri, "pmem_test_type_modules_bad", tmp_path, PMEM_TYPES="nope_mod")
    assert pmem(env, "info", "--help").returncode == 0
    assert pmem(env, "db", "status").returncode == 0


def test_an_installed_package_declares_its_types_by_entry_point(monkeypatch):
    from importlib import metadata

    from percept_memory.memory.types import modules

    point = metadata.EntryPoint("lab", "lab_pkg.types", modules.ENTRY_POINTS)
    monkeypatch.setattr(modules, "entry_points",
                        lambda group: [point] if group == modules.ENTRY_POINTS else [])
    monkeypatch.setattr(modules, "declared", cache(modules.declared.__wrapped__))  # (afresh)
    assert modules.type_modules("mine, lab_pkg.types") == {
        "lab_pkg.types": "PMEM_TYPES", "mine": "PMEM_TYPES"}
    assert modules.type_modules("") == {"lab_pkg.types": "the entry point 'lab' of a package"}
    with pytest.raises(modules.TypeModuleError, match="^the entry point 'lab' of a package: "
                                                      "cannot import 'lab_pkg.types'"):
        modules.import_type_modules("")


BUGGY = textwrap.dedent('''
    from percept_memory.memory.types import Annotation, stored_type

    @stored_type("lab.annotation.Grip")
    class Grip(Annotation):
        force: float

        def labels(self) -> list[str]:
            return ["firm"] if 10 / (self.force - 2.0) > 1 else []
''')


def test_a_type_whose_own_code_fails_is_named_not_a_server_error(mongo_uri, tmp_path,
                                                                 kitchen_rgb):
    """A type's labels() that raises on an annotation: a plain-text 500 (a small body or a
    large one, made by the worker processes) and a traceback from pmem reindex."""
    (tmp_path / "grip_types.py").write_text(BUGGY)
    db = "pmem_test_type_modules_buggy"
    env = pmem_env(mongo_uri, db, tmp_path, PMEM_TYPES="grip_types",
                   PMEM_INGEST_PROCESSES="2", PMEM_CONSOLIDATOR="false")
    port = free_port()
    server = subprocess.Popen([sys.executable, "-m", "percept_memory", "serve", "--port",
                               str(port)], env=env, stderr=subprocess.PIPE, text=True)
    gripped = {"_type": "lab.annotation.Grip", "source": "Gripper", "force": 2.0}
    try:
        base = f"http://127.0.0.1:{port}"
        wait_until_serving(f"{base}/api/schema/scene")
        for first, count in ((0, 1), (1, 24)):
            scenes = body_of(kitchen_rgb, first, count)
            scenes[-1]["clusters"][0]["annotations"].append(gripped)
            request = urllib.request.Request(f"{base}/api/scenes", json.dumps(scenes).encode(),
                                             {"Content-Type": "application/json"})
            with pytest.raises(urllib.error.HTTPError) as refused:
                urllib.request.urlopen(request, timeout=120)
            assert refused.value.code == 422, count
            message = json.load(refused.value)["error"]["message"]
            assert "lab.annotation.Grip.labels() failed on annotation" in message
            assert "ZeroDivisionError: float division by zero" in message
    finally:
        server.terminate()
        server.wait(timeout=30)
    assert "Traceback" not in server.stderr.read()
    try:  # stored by a process that knew no such type, then reindexed by one that does
        store = MemoryStore(MongoClient(mongo_uri, **CLIENT_OPTIONS), db, gridfs_threshold=2048)
        store.put_scene(Scene(timestamp=1, robot="gripper", clusters=[
            Cluster(annotations=[Unknown(type_name=gripped["_type"], fields=gripped)])]))
        done = pmem(env, "reindex")
        assert done.returncode == 0 and "Traceback" not in done.stderr, done.stderr
        assert "lab.annotation.Grip.labels() failed" in done.stderr
    finally:
        MongoClient(mongo_uri).drop_database(db)
