"""Server render time of the HTML pages; prints JSON.

A scene of 20 clusters (x 20 annotations, 64 px crops cut from the real kitchen frame, the
frame itself as the scene image) and 200 more scenes for the scene log, in a scratch database
on the configured or embedded mongod, dropped afterwards. Pages are fetched in-process through
the ASGI app (no network), so the time is reading + rendering. Target: scene page < 200 ms.

Usage: python bench/webui.py [--repeat N]
"""

from __future__ import annotations

import argparse
import json
import secrets
import statistics
import sys
import time

import numpy as np
from fastapi.testclient import TestClient
from ingest import kitchen_image  # bench/ingest.py, beside this file

from percept_memory.ingest import synthetic
from percept_memory.memory.settings import Settings
from percept_memory.memory.store import MemoryStore
from percept_memory.memory.types import Image
from percept_memory.webui.app import create_app

STAMP = 1_700_000_000_000_000_000


def timed(client: TestClient, path: str, repeat: int) -> dict:
    client.get(path).raise_for_status()  # warm
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        client.get(path).raise_for_status()
        times.append((time.perf_counter() - start) * 1000)
    times.sort()
    return {"median_ms": round(statistics.median(times), 1),
            "p95_ms": round(times[int(0.95 * (len(times) - 1))], 1)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeat", type=int, default=30)
    args = parser.parse_args()
    rng, image = np.random.default_rng(0), kitchen_image()
    big = synthetic.scene(rng, STAMP, clusters=20, image=image)
    if image is not None:
        big.images["color"] = Image(data=image)
    others = [synthetic.scene(rng, STAMP + (i + 1) * 10**9, image=image) for i in range(200)]
    settings = Settings(db=f"pmem_bench_{secrets.token_hex(4)}")
    store = MemoryStore.open(settings)
    try:
        store.put_scenes([big, *others])
        client = TestClient(create_app(store, settings))
        result = {
            "benchmark": "webui",
            "scene_page_20_clusters": timed(client, f"/scenes/{big.id}", args.repeat),
            "cluster_page": timed(client, f"/clusters/{big.clusters[0].id}", args.repeat),
            "scene_log_page": timed(client, "/", args.repeat),
            "crop_png": timed(client, f"/img/clusters/{big.clusters[0].id}/crop", args.repeat),
            "scene_thumbnail_png": timed(client, f"/img/scenes/{big.id}/thumb", args.repeat),
        }
    finally:
        store.client.drop_database(settings.db)
        store.close()
    json.dump(result, sys.stdout, indent=2)
    print()


if __name__ == "__main__":
    main()
