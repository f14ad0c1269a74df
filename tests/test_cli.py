"""`pmem info` and the CLI's errors, against real MongoDB servers."""

from __future__ import annotations

import json
import subprocess
import time

import numpy as np
import pytest
from click.testing import CliRunner
from pymongo import MongoClient

from percept_memory.cli import main
from percept_memory.ingest import synthetic
from percept_memory.memory.mongod import find_mongod

from .test_mongod import free_port


def pmem(*args: str, **env: str | None):
    return CliRunner().invoke(main, list(args), env=env)


def test_info_counts_what_the_store_holds(store, mongo_uri, db_name, kitchen_rgb):
    store.put_scene(synthetic.scene(np.random.default_rng(4), 1_000, 3, kitchen_rgb))
    result = pmem("info", "--json", MONGODB_URI=mongo_uri, PMEM_DB=db_name)
    assert result.exit_code == 0, result.output
    report = json.loads(result.stdout)
    assert report["database"] == db_name
    assert report["collections"]["scenes"] == 1
    assert report["collections"]["clusters"] == 3
    assert report["types"]["pm.annotation.WebLookup"] == 9  # 3 per synthetic cluster
    assert report["types"]["pm.hypothesis.ImageROI"] == 3

    human = pmem("info", MONGODB_URI=mongo_uri, PMEM_DB=db_name)
    assert human.exit_code == 0
    assert "pm.annotation.Classification" in human.stdout
    assert "clusters" in human.stdout


def test_info_on_an_unreachable_server_says_what_to_do():
    uri = f"mongodb://reader:s3cret@127.0.0.1:{free_port()}/?serverSelectionTimeoutMS=300"
    result = pmem("info", MONGODB_URI=uri)
    assert result.exit_code == 1
    assert "cannot use MongoDB at" in result.stderr and "MONGODB_URI" in result.stderr
    assert "s3cret" not in result.stderr and "Traceback" not in result.output


@pytest.fixture
def standalone_mongod(tmp_path):
    """A real mongod started without --replSet, as many installations run it."""
    port = free_port()
    process = subprocess.Popen(
        [str(find_mongod()), "--dbpath", str(tmp_path), "--port", str(port),
         "--bind_ip", "127.0.0.1", "--quiet", "--logpath", str(tmp_path / "log")],
    )
    uri = f"mongodb://127.0.0.1:{port}/?serverSelectionTimeoutMS=20000"
    with MongoClient(uri) as client:
        for _ in range(200):
            try:
                client.admin.command("ping")
                break
            except Exception:
                time.sleep(0.1)
    yield uri
    process.terminate()
    process.wait(30)


def test_a_standalone_server_is_refused_with_the_fix(standalone_mongod):
    result = pmem("info", MONGODB_URI=standalone_mongod)
    assert result.exit_code == 1
    assert "replica set" in result.stderr and "--replSet" in result.stderr
