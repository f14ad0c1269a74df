"""Sustained ingest benchmark; prints JSON.

Scenes of 6 clusters x 20 annotations with 64 px crops cut from the real kitchen frame go in
(a) in-process through IngestService.ingest_stream (batches, pipelined) and (b) over HTTP:
batches POSTed one at a time on loopback to `pmem serve` running in its own process, not
waiting for the belief, as a JSON array and as NDJSON (one scene a line): each once with the
server's own consolidator working beside (the default), once with it off
(PMEM_CONSOLIDATOR=false, as when `pmem consolidate` runs elsewhere). Targets: in-process
>= 2,000 clusters/s; HTTP >= 70 % of the in-process rate of the same run. Every ratio is
printed: `consolidator_apart` compares like with like (the in-process run stores scenes
without consolidating them), `consolidator_in_server` is what a default `pmem serve` gives on
the same cores, consolidating as it goes. All write to scratch databases on the
same mongod, dropped afterwards. This process collects garbage as pmem's do (collect_less).

Usage: python bench/ingest.py [--scenes N] [--batch N] [--http-scenes N]
"""

from __future__ import annotations

import argparse
import gc
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import cv2
import httpx2
import numpy as np
from rich.console import Console
from rich.progress import Progress
from scratch import footprint, print_json, scratch_store

from percept_memory.ingest import synthetic
from percept_memory.ingest.service import IngestService
from percept_memory.memory.settings import collect_less
from percept_memory.memory.store import MemoryStore

KITCHEN = Path(__file__).resolve().parents[2] / "shared/data/robosherlock/samples/kitchen"
CLUSTERS = 6
TARGET = 2000


def kitchen_image() -> np.ndarray | None:
    found = sorted(KITCHEN.glob("rgb_*.png"))
    return cv2.imread(str(found[0])) if found else None


def scenes(count: int, start: int, image, seed: int):
    rng = np.random.default_rng(seed)
    return [synthetic.scene(rng, start + i * 33_000_000, CLUSTERS, image) for i in range(count)]


def server_cpu_s(store: MemoryStore) -> float | None:
    """CPU seconds the MongoDB server has used (user + system), where it reports them."""
    info = store.client.admin.command("serverStatus").get("extra_info", {})
    if "user_time_us" not in info:
        return None
    return (info["user_time_us"] + info.get("system_time_us", 0)) / 1e6


def in_process(store: MemoryStore, count: int, batch: int, image, progress: Progress) -> dict:
    generated = scenes(count, 1_700_000_000_000_000_000, image, seed=1)
    # A robot streams scenes in; it does not hold a thousand of them at once. Freezing the
    # pre-generated ones keeps the garbage collector's work what it is in a stream (it would
    # otherwise walk these ~0.5 M objects on every full collection: 25 % of the time).
    gc.freeze()
    task = progress.add_task("in-process", total=count)
    service = IngestService(store, batch_size=batch)
    server_start, client_start = server_cpu_s(store), time.process_time()
    start = time.perf_counter()
    for _ in service.ingest_stream((str(i), s) for i, s in enumerate(generated)):
        progress.advance(task)
    seconds = time.perf_counter() - start
    clusters = count * CLUSTERS
    client_us = (time.process_time() - client_start) / clusters * 1e6
    server_end = server_cpu_s(store)
    server_us = None if server_end is None else (server_end - server_start) / clusters * 1e6
    return {
        "scenes": count,
        "batch": batch,
        "clusters_per_s": round(clusters / seconds),
        "annotations_per_s": round(clusters * 20 / seconds),
        "target_clusters_per_s": TARGET,
        "met": clusters / seconds >= TARGET,
        # Where the time goes: CPU per stored cluster in this process (encoding, the driver)
        # and in mongod (documents, index entries, oplog, journal), and the cores those take
        # at the target rate (this machine has os.cpu_count(), mongod included).
        "client_cpu_us_per_cluster": round(client_us),
        "mongod_cpu_us_per_cluster": None if server_us is None else round(server_us),
        "cores_needed_for_target": None if server_us is None else round(
            (client_us + server_us) * TARGET / 1e6, 2),
        "cores": os.cpu_count(),
    }


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


FORMATS = {  # media type, how a batch's scenes (JSON texts) make a body
    "json": ("application/json", lambda texts: "[" + ",".join(texts) + "]"),
    "ndjson": ("application/x-ndjson", lambda texts: "\n".join(texts) + "\n"),
}


def over_http(db: str, count: int, batch: int, image, progress: Progress,
              consolidator: bool, body_format: str) -> dict:
    generated = scenes(count + batch, 1_800_000_000_000_000_000, image, seed=2)
    media_type, joined = FORMATS[body_format]
    first, *bodies = [
        joined([s.model_dump_json(by_alias=True) for s in generated[i : i + batch]])
        for i in range(0, count + batch, batch)
    ]
    port = free_port()
    server = subprocess.Popen(
        [sys.executable, "-m", "percept_memory", "serve", "--port", str(port)],
        env={**os.environ, "PMEM_DB": db, "PMEM_MAX_REQUEST_MB": "256",
             "PMEM_CONSOLIDATOR": str(consolidator).lower()},
    )
    task = progress.add_task(f"over HTTP ({body_format})", total=count + batch)
    try:
        with httpx2.Client(base_url=f"http://127.0.0.1:{port}", timeout=120) as client:
            _wait_until_up(client)

            def post(body: str) -> None:
                response = client.post("/api/scenes", content=body,
                                       headers={"content-type": media_type})
                response.raise_for_status()
                progress.advance(task, len(response.json()["scenes"]))

            start = time.perf_counter()
            post(first)  # the server's first large body starts its ingest workers: untimed
            first_s = time.perf_counter() - start
            start = time.perf_counter()
            for body in bodies:
                post(body)
            seconds = time.perf_counter() - start
            pending = _pending(client)
            caught_up = _caught_up_s(client) if consolidator else None
    finally:
        server.terminate()
        server.wait(30)
    return {
        "body": media_type,
        "consolidator_in_server": consolidator,
        "scenes_pending_at_the_end": pending,
        # it gives way to ingest (memory/pipeline.py) and catches up after the burst
        "belief_caught_up_s_after_the_end": caught_up,
        "scenes": count,
        "batch": batch,
        "first_request_s": round(first_s, 2),  # not in the rate: it starts the workers
        "request_mb": round(sum(map(len, bodies)) / len(bodies) / 2**20, 2),
        "clusters_per_s": round(count * CLUSTERS / seconds),
        "requests_per_s": round(len(bodies) / seconds, 2),
    }


def _pending(client: httpx2.Client) -> int:
    return client.get("/api/pipeline").json()["maps"][0]["pending"]


def _caught_up_s(client: httpx2.Client, timeout: float = 600) -> float | None:
    """Seconds until no scene is pending (None: not within the timeout)."""
    start = time.perf_counter()
    while _pending(client):
        if time.perf_counter() - start > timeout:
            return None
        time.sleep(0.1)
    return round(time.perf_counter() - start, 1)


def _wait_until_up(client: httpx2.Client) -> None:
    for _ in range(300):
        try:
            client.get("/api/schema/scene").raise_for_status()
            return
        except httpx2.HTTPError:
            time.sleep(0.1)
    raise RuntimeError("pmem serve did not come up")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenes", type=int, default=1000)
    parser.add_argument("--batch", type=int, default=32)
    parser.add_argument("--http-scenes", type=int, default=300)
    args = parser.parse_args()
    collect_less()
    image = kitchen_image()
    with Progress(transient=True, console=Console(stderr=True)) as progress:
        with scratch_store() as store:
            local = in_process(store, args.scenes, args.batch, image, progress)
            local["footprint"] = footprint(store)
        http = {}
        for body_format in FORMATS:
            for consolidator in (True, False):
                with scratch_store() as store:
                    http[body_format, consolidator] = over_http(
                        store.db.name, args.http_scenes, args.batch, image, progress,
                        consolidator, body_format)
    ratios = {f"{body_format}_consolidator_{'in_server' if inside else 'apart'}":
              round(http[body_format, inside]["clusters_per_s"] / local["clusters_per_s"], 3)
              for body_format, inside in http}
    print_json({
        "benchmark": "ingest",
        "clusters_per_scene": CLUSTERS,
        "annotations_per_cluster": 20,
        "in_process": local,
        "http": http["json", True],
        "http_without_consolidator": http["json", False],
        "http_ndjson": http["ndjson", True],
        "http_ndjson_without_consolidator": http["ndjson", False],
        "http_to_in_process": ratios,
        "http_target": 0.7,
        "http_met": {name: ratio >= 0.7 for name, ratio in ratios.items()},
    })


if __name__ == "__main__":
    main()
