"""What every benchmark does around its measurements: a scratch database on the configured (or
embedded) mongod, dropped afterwards unless kept, and the result as JSON on stdout."""

from __future__ import annotations

import json
import secrets
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from percept_memory.memory.settings import Settings
from percept_memory.memory.store import MemoryStore


@contextmanager
def scratch_store(keep: str | None = None, **settings: Any) -> Iterator[MemoryStore]:
    """A store on a fresh database, dropped on exit; or on the database `keep`, built once
    and kept for the next run."""
    store = MemoryStore.open(Settings(db=keep or f"pmem_bench_{secrets.token_hex(4)}",
                                      **settings))
    try:
        yield store
    finally:
        if not keep:
            store.client.drop_database(store.db.name)
        store.close()


def footprint(store: MemoryStore) -> dict:
    """What the memory takes per stored cluster (every collection of its database counted):
    documents as BSON, on disk (compressed), indexes; the cluster collection's largest
    indexes; and mongod's resident memory (the whole server's, other databases included)."""
    clusters = max(store.clusters.estimated_document_count(), 1)
    store.client.admin.command("fsync")  # a checkpoint: sizes on disk count what is written
    db = store.db.command("dbStats")
    indexes = store.db.command("collStats", store.clusters.name)["indexSizes"]
    status = store.client.admin.command("serverStatus")
    return {
        "clusters": clusters,
        "data_bytes_per_cluster": round(db["dataSize"] / clusters),
        "storage_bytes_per_cluster": round(db["storageSize"] / clusters),
        "index_bytes_per_cluster": round(db["indexSize"] / clusters),
        "largest_cluster_indexes_bytes_per_cluster": {
            name: round(size / clusters) for name, size in
            sorted(indexes.items(), key=lambda item: -item[1])[:5]},
        "mongod_resident_mb": status["mem"].get("resident"),
        "mongod_cache_mb": round(status["wiredTiger"]["cache"]["bytes currently in the cache"]
                                 / 2**20),
    }


def print_json(result: dict, indent: int = 2) -> None:
    json.dump(result, sys.stdout, indent=indent)
    print()
