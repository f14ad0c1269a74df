"""Memory pipeline benchmark: how fast the belief follows what is stored; prints JSON.

(a) Throughput: scenes are stored with no consolidator running, then one consolidator
    (memory/pipeline.py, the code of the server's thread and of `pmem consolidate`) works the
    backlog off: scenes/s (target >= 100 scenes of 6 clusters). Two workloads: a generated
    kitchen (kitchen_week: 20 objects moved about, ~4 clusters a scene, a few annotations
    each) and bench/ingest.py's scenes (6 clusters x 20 annotations with crops, VFH,
    histograms, all seen by one camera pose).
(b) Belief lag through the user's path: `pmem serve` in its own process (its consolidator in
    a thread, the default), a robot POSTing one scene per request at a steady rate (default
    10 scenes/s, no waiting); a watcher polls GET /api/pipeline every 20 ms and notes when the
    map's `consolidated_until` passes each scene. Lag = that moment - the POST's answer
    (target p95 < 2 s). Each on a scratch database of the configured or embedded mongod.

Usage: python bench/pipeline.py [--days N] [--synthetic-scenes N] [--lag-scenes N] [--rate R]
                               [--seed S]
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import threading
import time

import httpx2
from ingest import _wait_until_up, free_port, kitchen_image, scenes
from rich.console import Console
from rich.progress import Progress
from scratch import print_json, scratch_store

from percept_memory.demo import kitchen_week
from percept_memory.ingest.service import IngestService, memory_pipeline
from percept_memory.memory.settings import collect_less


def throughput(scenes: list, progress: Progress) -> dict:
    clusters = sum(len(s.clusters) for s in scenes)
    with scratch_store() as store:
        service = IngestService(store)
        list(service.ingest_stream((str(i), s) for i, s in enumerate(scenes)))
        task = progress.add_task("consolidating", total=len(scenes))
        pipeline = memory_pipeline(store)
        stage_cpu = timed_stages(pipeline)
        start, cpu = time.perf_counter(), time.thread_time()
        done = pipeline.drain(progress=lambda n: progress.advance(task, n))
        seconds, cpu = time.perf_counter() - start, time.thread_time() - cpu
        objects = store.db["objects"].count_documents({})
    return {"scenes": done, "clusters_per_scene": round(clusters / len(scenes), 2),
            "seconds": round(seconds, 2), "scenes_per_s": round(done / seconds, 1),
            "clusters_per_s": round(clusters / seconds), "objects": objects,
            # where a scene's time goes: the consolidator's CPU, by stage (the rest of the
            # wall time is mongod's work and the round trips to it)
            "cpu_ms_per_scene": {"all": round(cpu / done * 1e3, 2),
                                 **{name: round(s / done * 1e3, 2)
                                    for name, s in stage_cpu.items()}},
            "target_scenes_per_s": 100, "met": done / seconds >= 100}


def timed_stages(pipeline) -> dict[str, float]:
    """The CPU seconds (of the consolidating thread) each stage of the pipeline spends, filled
    in as it runs; the catalogue, learnt inside identity's stage scene by scene, apart (and
    not in identity's)."""
    spent = {stage.name: 0.0 for stage in pipeline.stages}
    for stage in pipeline.stages:
        def timed(*args, apply=stage.apply, name=stage.name, **kwargs):
            start = time.thread_time()
            try:
                return apply(*args, **kwargs)
            finally:
                spent[name] += time.thread_time() - start
        stage.apply = timed
        if getattr(stage, "catalogue", None):
            def learnt(wall, cpu, name=stage.name):
                spent["catalogue"] = spent.get("catalogue", 0.0) + cpu
                spent[name] -= cpu
            timing_catalogue(stage, learnt)
    return spent


def timing_catalogue(identity, spent) -> None:
    """Time the catalogue's learning inside identity's stage (its batch's start, each scene's
    learning, its writes): spent(wall seconds, this thread's CPU seconds) after each."""
    def timed(call):
        def timed_call(*args, **kwargs):
            start, cpu = time.perf_counter(), time.thread_time()
            try:
                return call(*args, **kwargs)
            finally:
                spent(time.perf_counter() - start, time.thread_time() - cpu)
        return timed_call

    begin = timed(identity.catalogue.begin)

    def timed_begin(*args, **kwargs):
        batch = begin(*args, **kwargs)
        batch.observe, batch.finish = timed(batch.observe), timed(batch.finish)
        return batch
    identity.catalogue.begin = timed_begin


def lag(scenes: int, rate: float, seed: int, progress: Progress) -> dict:
    week = kitchen_week.generate(days=max(1, scenes // 30 + 1), seed=seed)
    bodies = [s.model_dump_json(by_alias=True, exclude={"id"}) for s in week.scenes[:scenes]]
    times = [s.timestamp for s in week.scenes[:scenes]]
    with scratch_store() as store:
        port = free_port()
        server = subprocess.Popen([sys.executable, "-m", "percept_memory", "serve", "--port",
                                   str(port)], env={**os.environ, "PMEM_DB": store.db.name})
        acknowledged: dict[int, float] = {}
        consolidated: dict[int, float] = {}
        stop = threading.Event()
        url = f"http://127.0.0.1:{port}"

        def watch() -> None:
            with httpx2.Client(base_url=url, timeout=30) as watcher:
                while not stop.is_set():
                    rows = watcher.get("/api/pipeline").json()["maps"]
                    now = time.perf_counter()
                    until = rows[0]["consolidated_until_ns"] if rows else None
                    for t in times:
                        if until is not None and t <= until and t not in consolidated:
                            consolidated[t] = now
                    time.sleep(0.02)

        task = progress.add_task(f"posting at {rate:g} scenes/s", total=scenes)
        try:
            with httpx2.Client(base_url=url, timeout=60) as client:
                _wait_until_up(client)
                watcher = threading.Thread(target=watch, daemon=True)
                watcher.start()
                start = time.perf_counter()
                for i, (body, t) in enumerate(zip(bodies, times, strict=True)):
                    time.sleep(max(0.0, start + i / rate - time.perf_counter()))
                    client.post("/api/scenes", content=body,
                                headers={"content-type": "application/json"}
                                ).raise_for_status()
                    acknowledged[t] = time.perf_counter()
                    progress.advance(task)
                sent = time.perf_counter() - start
                deadline = time.perf_counter() + 60
                while len(consolidated) < len(times) and time.perf_counter() < deadline:
                    time.sleep(0.05)
        finally:
            stop.set()
            server.terminate()
            server.wait(30)
    lags = sorted(consolidated[t] - acknowledged[t] for t in times if t in consolidated)
    p95 = lags[int(0.95 * (len(lags) - 1))] if lags else None
    return {"scenes": scenes, "rate_asked": rate, "rate_sent": round(scenes / sent, 2),
            "consolidated": len(lags),
            "lag_s": {"p50": round(statistics.median(lags), 3), "p95": round(p95, 3),
                      "max": round(lags[-1], 3)} if lags else None,
            "target_p95_s": 2.0, "met": p95 is not None and p95 < 2.0 and len(lags) == scenes}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--days", type=int, default=30, help="kitchen days for (a)")
    parser.add_argument("--synthetic-scenes", type=int, default=1000, help="6x20 scenes for (a)")
    parser.add_argument("--lag-scenes", type=int, default=600, help="scenes posted in (b)")
    parser.add_argument("--rate", type=float, default=10.0, help="scenes/s posted in (b)")
    parser.add_argument("--seed", type=int, default=11)
    args = parser.parse_args()
    collect_less()  # as `pmem consolidate` does
    with Progress(transient=True, console=Console(stderr=True)) as progress:
        kitchen = kitchen_week.generate(days=args.days, seed=args.seed).scenes
        synthetic = scenes(args.synthetic_scenes, 1_700_000_000_000_000_000, kitchen_image(),
                           args.seed)
        print_json({"benchmark": "pipeline",
                    "throughput": {"kitchen": throughput(kitchen, progress),
                                   "synthetic_6x20": throughput(synthetic, progress)},
                    "belief_lag_over_http": lag(args.lag_scenes, args.rate, args.seed,
                                                progress)})


if __name__ == "__main__":
    main()
