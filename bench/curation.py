"""Corrections by people, through their path: prints JSON.

On the kitchen week (--days days, consolidated) in a scratch database:
- keyboard: 20 labels corrected from the review queue in headless Chromium (Debian's
  /usr/bin/chromium) by keyboard, against a real uvicorn server: the whole run from the first
  key to the 20th "Saved." and each correction's Enter-to-saved time (Playwright types without
  a person's pauses, so this is the app's share of a person's time, not the person's);
- review_page: the server's render time of /review over the latest 500 scenes;
- rejection: a rejection asks for its map's belief to be rebuilt; the time until the pipeline
  has rebuilt it (the whole map: the cost grows with the map's scenes), and the same for the
  undo;
- split: the latest half of the observations of the object seen most often split off (a
  rebuild too), and how many of them identity then kept off every object an observation of
  the rest was taken for (all, if it did as asked).

Usage: python bench/curation.py [--days N] [--repeat N]
"""

from __future__ import annotations

import argparse
import socket
import statistics
import threading
import time
from contextlib import contextmanager

import uvicorn
from fastapi.testclient import TestClient
from playwright.sync_api import expect, sync_playwright
from scratch import print_json, scratch_store

from percept_memory.demo import kitchen_week
from percept_memory.ingest.service import IngestService, memory_pipeline
from percept_memory.memory import curation
from percept_memory.memory.settings import Settings
from percept_memory.queries.review import review_queue
from percept_memory.webui.app import create_app

CHROMIUM = "/usr/bin/chromium"
CORRECTIONS = 20


@contextmanager
def serving(app):
    """The app on a free loopback port, in a thread: its base URL."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port,
                                           log_level="warning"))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    while not server.started:
        time.sleep(0.05)
    try:
        yield f"http://127.0.0.1:{port}"
    finally:
        server.should_exit = True
        thread.join(10)


def ms(seconds: float) -> float:
    return round(seconds * 1000, 1)


def summary(times: list[float]) -> dict:
    ordered = sorted(times)
    return {"n": len(ordered), "p50_ms": ms(statistics.median(ordered)),
            "p95_ms": ms(ordered[min(len(ordered) - 1, round(0.95 * (len(ordered) - 1)))]),
            "max_ms": ms(ordered[-1])}


def by_keyboard(url: str) -> dict:
    """20 corrections from the review queue, by keyboard."""
    with sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path=CHROMIUM, args=[
            "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking"])
        tab = browser.new_page()
        tab.goto(f"{url}/review?shown={CORRECTIONS}")
        tab.locator("#author").fill("bench")
        rows = tab.locator("table.review tbody tr")
        rows.first.locator("input[name=label]").focus()
        each = []
        start = time.perf_counter()
        for number in range(CORRECTIONS):
            tab.keyboard.type(f"thing {number}")
            sent = time.perf_counter()
            tab.keyboard.press("Enter")
            expect(rows.nth(number).locator("form.relabel [role=status]")).to_have_text("Saved.")
            each.append(time.perf_counter() - sent)
        total = time.perf_counter() - start
        browser.close()
    return {"corrections": CORRECTIONS, "total_s": round(total, 2),
            "enter_to_saved": summary(each)}


def rebuilt_after(store, change) -> float:
    """Seconds from a correction to its map's belief rebuilt by the pipeline."""
    pipeline = memory_pipeline(store)
    start = time.perf_counter()
    change()
    pipeline.drain()
    return round(time.perf_counter() - start, 2)


def split_off(store) -> tuple[float, dict]:
    """The latest half of the observations of the object seen most often, split off: seconds
    until the map is rebuilt, and how many of them identity then kept apart as asked."""
    seen = store.objects.find_one(sort=[("observations", -1)])
    theirs = [c["_id"] for c in store.clusters.find({"object_id": seen["_id"]}).sort(
        "search.time", 1)]
    earlier, later = theirs[:len(theirs) // 2], theirs[len(theirs) // 2:]
    seconds = rebuilt_after(store, lambda: curation.split(store, seen["_id"], later,
                                                          author="bench"))
    objects = {c["_id"]: c.get("object_id") for c in store.clusters.find(
        {"_id": {"$in": theirs}}, {"object_id": 1})}
    rest = {objects[c] for c in earlier}
    apart = sum(objects[c] not in rest for c in later)
    return seconds, {"observations": len(theirs), "split_off": len(later), "kept_apart": apart,
                     "objects_now": len(set(objects.values()))}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--days", type=int, default=7)
    parser.add_argument("--repeat", type=int, default=20)
    args = parser.parse_args()
    with scratch_store() as store:
        week = kitchen_week.generate(days=args.days)
        service = IngestService(store)
        list(service.ingest_stream((str(i), s) for i, s in enumerate(week.scenes)))
        service.pipeline.drain()
        app = create_app(store, Settings(consolidator=False))
        client = TestClient(app, base_url="http://127.0.0.1")
        client.get("/review").raise_for_status()
        page_times = []
        for _ in range(args.repeat):
            start = time.perf_counter()
            client.get("/review").raise_for_status()
            page_times.append(time.perf_counter() - start)
        with serving(app) as url:
            keyboard = by_keyboard(url)
        doubt = review_queue(store, shown=1).doubts[0]
        made = []
        reject_s = rebuilt_after(store, lambda: made.append(
            curation.reject(store, doubt.cluster_id, author="bench")))
        undo_s = rebuilt_after(store, lambda: curation.undo(store, doubt.cluster_id,
                                                              made[0].id, author="bench"))
        split_s, kept_apart = split_off(store)
        print_json({
            "days": args.days, "scenes": len(week.scenes),
            "clusters": store.clusters.estimated_document_count(),
            "keyboard": keyboard,
            "review_page": {"window_scenes": 500, **summary(page_times)},
            "rejection": {"map_rebuilt_s": reject_s, "undo_map_rebuilt_s": undo_s},
            "split": {"map_rebuilt_s": split_s, **kept_apart},
        })


if __name__ == "__main__":
    main()
