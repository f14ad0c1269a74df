"""Sustained ingest benchmark; prints JSON.

Scenes of 6 clusters x 20 annotations with 64 px crops cut from the real kitchen frame go in
(a) in-process through IngestService.ingest_stream (batches, pipelined) and (b) over HTTP:
batches POSTed one at a time on loopback to `pmem serve` running in its own process, not
waiting for the belief, as a JSON array and as NDJSON (one scene a line): each once with the
server's own consolidator working beside (the default), once with it off
(PMEM_CONSOLIDATOR=false, as when `pmem consolidate` runs elsewhere). Targets: in-process
>= 2,000 clusters/s; HTTP >= 70 % of the in-process rate of the same run.

A shared machine's speed drifts by tens of percent from one minute to the next, so the five
ways are measured in rounds (`--rounds`), each the same number of scenes on a fresh scratch
database, one after the other within the round; each HTTP rate is divided by its own round's
in-process rate, and the medians and ranges of rates and ratios are printed, every round's
too. `consolidator_apart` compares like with like (the in-process run stores scenes without
consolidating them); `consolidator_in_server` is what a default `pmem serve` gives on the
same cores, consolidating as it goes. All write to scratch databases on the same mongod,
dropped afterwards. This process collects garbage as pmem's do (collect_less).

Usage: python bench/ingest.py [--scenes N] [--batch N] [--rounds N]
"""

from __future__ import annotations

import argparse
import gc
import os
import socket
import statistics
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


WAYS = [(body_format, consolidator) for body_format in FORMATS
        for consolidator in (True, False)]


def way_name(body_format: str, consolidator: bool) -> str:
    return f"{body_format}_consolidator_{'in_server' if consolidator else 'apart'}"


def spread(values: list[float]) -> dict:
    return {"median": round(statistics.median(values), 3), "min": round(min(values), 3),
            "max": round(max(values), 3)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenes", type=int, default=320, help="scenes per run, every way")
    parser.add_argument("--batch", type=int, default=32)
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args()
    collect_less()
    image = kitchen_image()
    rounds = []
    with Progress(transient=True, console=Console(stderr=True)) as progress:
        for number in range(args.rounds):
            with scratch_store() as store:
                local = in_process(store, args.scenes, args.batch, image, progress)
                if not number:
                    local["footprint"] = footprint(store)
            http = {}
            for body_format, consolidator in WAYS:
                with scratch_store() as store:
                    http[way_name(body_format, consolidator)] = over_http(
                        store.db.name, args.scenes, args.batch, image, progress,
                        consolidator, body_format)
            rounds.append({"in_process": local, "http": http, "http_to_in_process": {
                name: round(run["clusters_per_s"] / local["clusters_per_s"], 3)
                for name, run in http.items()}})
    ratios = {name: spread([r["http_to_in_process"][name] for r in rounds])
              for name in rounds[0]["http"]}
    in_process_rates = spread([r["in_process"]["clusters_per_s"] for r in rounds])
    print_json({
        "benchmark": "ingest",
        "clusters_per_scene": CLUSTERS,
        "annotations_per_cluster": 20,
        "scenes_per_run": args.scenes,
        "rounds": args.rounds,
        "in_process_clusters_per_s": in_process_rates,
        "in_process_target": TARGET,
        "in_process_met": in_process_rates["median"] >= TARGET,
        "http_clusters_per_s": {name: spread([r["http"][name]["clusters_per_s"]
                                              for r in rounds]) for name in ratios},
        "http_to_in_process": ratios,
        "http_target": 0.7,
        "http_met": {name: ratio["median"] >= 0.7 for name, ratio in ratios.items()},
        "each_round": rounds,
    })


if __name__ == "__main__":
    main()
