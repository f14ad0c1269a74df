"""Shared fixtures: a real MongoDB for the session and a fresh database per test module."""

from __future__ import annotations

import os
import secrets
import socket
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import cv2
import numpy as np
import pytest
from pymongo import MongoClient

from percept_memory.memory.mongod import EmbeddedMongod
from percept_memory.memory.settings import Settings
from percept_memory.memory.store import CLIENT_OPTIONS, MemoryStore


@pytest.fixture(scope="session")
def mongo_uri(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """MONGODB_URI if set (CI can point at any server), else a real embedded mongod."""
    if uri := os.environ.get("MONGODB_URI"):
        yield uri
        return
    with socket.socket() as probe:  # a free loopback port, chosen by the kernel
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    mongod = EmbeddedMongod(tmp_path_factory.mktemp("mongod"), port, cache_gb=0.25, oplog_mb=64)
    try:
        yield mongod.start()
    finally:
        mongod.stop()


@pytest.fixture(scope="module")
def db_name(request: pytest.FixtureRequest, mongo_uri: str) -> Iterator[str]:
    """A database name unique to the test module, dropped when the module is done."""
    module = request.module.__name__.rsplit(".", 1)[-1].removeprefix("test_")
    name = f"test_{module[:40]}_{secrets.token_hex(4)}"
    yield name
    with MongoClient(mongo_uri) as client:
        client.drop_database(name)


LOCAL = "http://127.0.0.1"
"""The base URL of TestClients: a Host the app answers (guard.py), unlike the default testserver."""

# --- the memory store and the real RoboSherlock data ------------------------------------------

SHARED = Path(os.environ.get("PMEM_SHARED", Path(__file__).resolve().parents[2] / "shared"))
ROBOSHERLOCK = SHARED / "data" / "robosherlock"


@pytest.fixture(scope="module")
def store(mongo_uri: str, db_name: str) -> Iterator[MemoryStore]:
    """A MemoryStore on the module's fresh database."""
    client = MongoClient(mongo_uri, **CLIENT_OPTIONS)
    memory = MemoryStore(client, db_name, gridfs_threshold=Settings().gridfs_threshold)
    memory.prepare()
    yield memory
    memory.close()


@pytest.fixture(scope="session")
def kitchen_rgb() -> np.ndarray:
    """The real 640x480 kitchen counter frame of RoboSherlock's samples (BGR, uint8)."""
    (path,) = (ROBOSHERLOCK / "samples" / "kitchen").glob("rgb_*.png")
    return cv2.imread(str(path), cv2.IMREAD_UNCHANGED)


def ingest_consolidated(store: MemoryStore, scenes) -> None:
    """Ingest scenes as an importer does and wait for the pipeline to consolidate them."""
    from percept_memory.ingest.service import IngestService

    service = IngestService(store)
    list(service.ingest_stream((str(i), scene) for i, scene in enumerate(scenes)))
    service.pipeline.drain(timeout=600)
    assert not service.pipeline.pending()


@pytest.fixture(scope="module")
def kitchen(store):
    """The generated kitchen week ingested with consolidation into the module's store, and the
    ground truth of every stored cluster: cluster id -> the catalogue object it shows."""
    from percept_memory.demo import kitchen_week

    week = kitchen_week.generate()
    ingest_consolidated(store, week.scenes)
    truth_of = {cluster.id: week.truth.object_at(i, j)
                for i, scene in enumerate(week.scenes) for j, cluster in enumerate(scene.clusters)}
    return week, truth_of


@contextmanager
def served(app) -> Iterator[str]:
    """A real uvicorn server of `app` on a free loopback port, in a thread: its base URL."""
    import uvicorn

    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port,
                                           log_level="warning"))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + 20
    while not server.started:
        assert time.monotonic() < deadline and thread.is_alive(), "uvicorn did not start"
        time.sleep(0.05)
    yield f"http://127.0.0.1:{port}"
    server.should_exit = True
    thread.join(10)
