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


def print_json(result: dict, indent: int = 2) -> None:
    json.dump(result, sys.stdout, indent=indent)
    print()
