"""The HTML pages: a newcomer's flow in a real headless Chromium (Playwright) against a real
uvicorn server on the kitchen week (consolidated) and the real RoboSherlock kitchen frame, plus
plain HTTP checks of escaping, the Content-Security-Policy and bad URLs.

Chromium is Debian's (`apt-get install chromium`; .ci/run installs it). Screenshots go to
test-output/screenshots/.
"""

from __future__ import annotations

import html
import re
import socket
import threading
import time
from collections import Counter
from pathlib import Path

import pytest
import uvicorn
from bson import ObjectId
from fastapi.testclient import TestClient
from playwright.sync_api import Page, expect, sync_playwright

from percept_memory.ingest import kitchen_week
from percept_memory.ingest.rgbd import read_samples
from percept_memory.ingest.service import IngestService
from percept_memory.memory.consolidation import Consolidator
from percept_memory.memory.settings import Settings
from percept_memory.memory.types import (
    Classification,
    Cluster,
    ImageROI,
    LogLine,
    Scene,
    Text,
    WebLookup,
)
from percept_memory.webui.app import create_app

from .conftest import ROBOSHERLOCK

CHROMIUM = Path("/usr/bin/chromium")
SCREENSHOTS = Path(__file__).resolve().parents[1] / "test-output" / "screenshots"
HOSTILE = "<script>alert('pwned')</script>"
HOSTILE_STAMP = 946_684_800_000_000_000  # 2000-01-01: older than every other scene
ALL_LOADED = "Array.from(document.images).every(i => i.complete && i.naturalWidth > 0)"


@pytest.fixture(scope="module")
def week():
    return kitchen_week.generate(days=1)


@pytest.fixture(scope="module")
def sample():
    """The real RoboSherlock kitchen frame with the objects found on the counter."""
    (scene,) = read_samples(ROBOSHERLOCK / "samples" / "kitchen", robot="pr2-sample")
    return scene


@pytest.fixture(scope="module")
def hostile():
    """A scene whose annotators said things a browser must not run."""
    roi = ImageROI(box=(0, 0, 2, 2))
    cluster = Cluster(hypotheses=[roi], annotations=[
        Text(text=HOSTILE, source="OCRAnnotator"),
        Classification(class_name=HOSTILE, confidence=0.5),
        WebLookup(category="text", title="evil", links=["javascript:alert(1)",
                                                        "https://example.org/a?b=<i>"]),
        {"_type": "rs.annotation.Segment", "label": "<b>bold</b>", "score": 0.25},  # unknown
    ])
    return Scene(timestamp=HOSTILE_STAMP, robot="mallory", clusters=[cluster],
                 log=[LogLine(source="OCRAnnotator", message=f"read {HOSTILE}")])


@pytest.fixture(scope="module")
def filled(store, week, sample, hostile):
    items = [(str(i), scene) for i, scene in enumerate(week.scenes)]
    list(IngestService(store, after_store=[Consolidator(store)]).ingest_stream(items))
    store.put_scenes([sample, hostile])  # not consolidated: clusters without an object
    return store


@pytest.fixture(scope="module")
def client(filled):
    return TestClient(create_app(filled, Settings()))


@pytest.fixture(scope="module")
def url(filled):
    """A real uvicorn server on a free loopback port, in a thread."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    server = uvicorn.Server(uvicorn.Config(create_app(filled, Settings()), host="127.0.0.1",
                                           port=port, log_level="warning"))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + 20
    while not server.started:
        assert time.monotonic() < deadline and thread.is_alive(), "uvicorn did not start"
        time.sleep(0.05)
    yield f"http://127.0.0.1:{port}"
    server.should_exit = True
    thread.join(10)


@pytest.fixture(scope="module")
def browser():
    assert CHROMIUM.exists(), "install Debian's chromium: apt-get install -y chromium"
    with sync_playwright() as playwright:
        chromium = playwright.chromium.launch(
            executable_path=str(CHROMIUM),
            args=["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking"],
        )
        yield chromium
        chromium.close()


@pytest.fixture
def page(browser) -> Page:
    context = browser.new_context(viewport={"width": 1280, "height": 900})
    tab = context.new_page()
    blocked: list[str] = []
    tab.on("console", lambda m: blocked.append(m.text) if "Content Security" in m.text else None)
    yield tab
    context.close()
    assert not blocked, f"the page broke its own Content-Security-Policy: {blocked}"


def shot(page: Page, name: str) -> None:
    SCREENSHOTS.mkdir(parents=True, exist_ok=True)
    page.screenshot(path=str(SCREENSHOTS / f"{name}.png"), full_page=True)


def images_decode(page: Page) -> None:
    page.wait_for_load_state("load")
    assert page.locator("img").count() > 0
    assert page.evaluate(ALL_LOADED), "an image did not decode"


# --- in the browser ---------------------------------------------------------------------------

def test_scene_log_to_scene_to_cluster_to_object_and_back(page, url, store, week):
    newest = sorted(week.scenes, key=lambda s: s.timestamp, reverse=True)

    page.goto(url + "/")
    rows = page.locator("tr.scene")
    expect(rows).to_have_count(20)
    assert rows.first.get_attribute("data-scene") == str(newest[0].id)
    shown = [int(rows.nth(i).locator("td.clusters").inner_text()) for i in range(20)]
    assert shown == [len(s.clusters) for s in newest[:20]]
    images_decode(page)
    shot(page, "1-scene-log")

    page.get_by_role("link", name="older scenes").click()
    expect(page.locator("tr.scene").first).to_have_attribute("data-scene", str(newest[20].id))
    page.go_back()

    scene = newest[0]
    page.locator("tr.scene").first.get_by_role("link").click()
    expect(page).to_have_url(f"{url}/scenes/{scene.id}")
    expect(page.locator("article.cluster")).to_have_count(len(scene.clusters))
    expect(page.locator(".cluster-count")).to_have_text(str(len(scene.clusters)))
    annotators = {line.source for line in scene.log}
    expect(page.locator("details.log")).to_have_count(len(annotators))
    images_decode(page)
    shot(page, "2-scene")

    cluster = scene.clusters[0]
    page.locator("#cluster-1 h3 a").click()
    expect(page).to_have_url(f"{url}/clusters/{cluster.id}")
    stored = store.get_cluster(cluster.id)
    expect(page.locator("code.phash")).to_have_text(stored.hypothesis_of(ImageROI).phash)
    event = store.db.events.find_one({"cluster_id": cluster.id})
    expect(page.locator("table.events .explanation")).to_have_text(event["explanation"])
    images_decode(page)
    shot(page, "3-cluster")

    believed = store.db.objects.find_one({"_id": stored.object_id})
    page.locator("a.object-link").click()
    expect(page).to_have_url(f"{url}/objects/{believed['_id']}")
    expect(page.locator("h1")).to_contain_text(believed["name"])
    history = list(store.db.events.find({"object_id": believed["_id"]}))
    expect(page.locator("table.history tbody tr")).to_have_count(len(history))
    kinds = Counter(e["explanation"] for e in history)
    for explanation, count in kinds.items():
        expect(page.locator(f"table.history .explanation.{explanation}")).to_have_count(count)
    crops = sum(1 for e in history if e.get("cluster_id"))
    expect(page.locator("ol.crops img")).to_have_count(crops)
    images_decode(page)
    shot(page, "4-object")

    page.go_back()
    expect(page).to_have_url(f"{url}/clusters/{cluster.id}")
    page.go_back()
    expect(page).to_have_url(f"{url}/scenes/{scene.id}")


def test_scene_image_with_numbered_cluster_boxes(page, url, sample):
    page.goto(f"{url}/scenes/{sample.id}")
    image = page.get_by_role("img", name=re.compile("color image of the scene"))
    images_decode(page)
    assert image.evaluate("i => i.naturalWidth") == sample.images["color"].width
    boxes = page.locator("a.box rect")
    expect(boxes).to_have_count(len(sample.clusters))
    for i, cluster in enumerate(sample.clusters):
        x, y, w, h = cluster.hypothesis_of(ImageROI).box
        assert [boxes.nth(i).get_attribute(k) for k in ("x", "y", "width", "height")] == \
            [str(x), str(y), str(w), str(h)]
    expect(page.locator("a.box text").first).to_have_text("1")
    expect(page.locator(".object-link")).to_have_count(0)  # not consolidated
    page.locator("a.box").nth(1).click()
    expect(page).to_have_url(f"{url}/scenes/{sample.id}#cluster-2")
    shot(page, "5-scene-image")


def test_keyboard_reaches_the_content(page, url):
    page.goto(url + "/")
    page.keyboard.press("Tab")
    expect(page.locator(":focus")).to_have_text("Skip to content")
    page.keyboard.press("Enter")
    for _ in range(8):
        page.keyboard.press("Tab")
    assert page.evaluate("document.activeElement.closest('main') !== null")


# --- plain HTTP -------------------------------------------------------------------------------

def test_untrusted_text_is_escaped(client, hostile):
    for path in (f"/scenes/{hostile.id}", f"/clusters/{hostile.clusters[0].id}",
                 "/scenes?robot=mallory"):
        body = client.get(path).text
        assert "<script>" not in body and "&lt;script&gt;" in body, path
    scene = client.get(f"/scenes/{hostile.id}").text
    assert 'href="javascript:' not in scene and "javascript:alert(1)" in scene
    assert 'href="https://example.org/a?b=&lt;i&gt;"' in scene


def test_unknown_annotation_types_render_as_field_tables(client, hostile):
    scene = client.get(f"/scenes/{hostile.id}").text
    assert "rs.annotation.Segment" in scene and "&lt;b&gt;bold&lt;/b&gt;" in scene
    assert '<meter min="0" max="1" value="0.25">' in scene


def test_every_page_sends_a_content_security_policy(client, week, hostile):
    scene = week.scenes[0]
    paths = ["/", "/scenes", f"/scenes/{scene.id}", f"/clusters/{scene.clusters[0].id}",
             f"/objects/{scene.clusters[0].object_id}", "/scenes/nonsense", "/?since=never"]
    for path in paths:
        response = client.get(path)
        assert response.headers["content-type"].startswith("text/html"), path
        policy = response.headers["content-security-policy"]
        assert "default-src 'none'" in policy and "script-src" not in policy, path


@pytest.mark.parametrize("path, status", [
    ("/scenes/nonsense", 404), (f"/scenes/{ObjectId()}", 404), ("/scenes/%3Cscript%3E", 404),
    ("/clusters/123", 404), (f"/clusters/{ObjectId()}", 404),
    ("/objects/zz", 404), (f"/objects/{ObjectId()}", 404),
    ("/img/scenes/nonsense/thumb", 404), (f"/img/clusters/{ObjectId()}/crop", 404),
    ("/?since=yesterday", 422), ("/?until=2024-13-01", 422), ("/?before=123", 422),
    ("/?before=99999999999999999999-0123456789abcdef01234567", 422), ("/?before=-", 422),
])
def test_bad_urls_get_a_page_naming_the_problem(client, path, status):
    response = client.get(path)
    assert response.status_code == status, response.text
    assert response.headers["content-type"].startswith("text/html")
    assert 'role="alert"' in response.text


def test_missing_images_are_404(client, hostile, sample):
    assert client.get(f"/img/scenes/{sample.id}/images/nothing").status_code == 404
    assert client.get(f"/img/clusters/{hostile.clusters[0].id}/crop").status_code == 404
    depth = client.get(f"/img/scenes/{sample.id}/images/depth")
    assert depth.status_code == 200 and depth.content.startswith(b"\x89PNG")


def older_link(body: str) -> str | None:
    found = re.search(r'class="older" href="([^"]+)"', body)
    return html.unescape(found.group(1)) if found else None


def test_pages_walk_every_scene_once_newest_first(client, store):
    expected = [d["_id"] for d in store.scenes.find({}, {"_id": 1}).sort(
        [("timestamp", -1), ("_id", -1)])]
    seen, path = [], "/"
    while path:
        body = client.get(path).text
        seen += [ObjectId(s) for s in re.findall(r'data-scene="([0-9a-f]{24})"', body)]
        path = older_link(body)
    assert seen == expected


def test_filters_by_robot_and_time(client, week):
    body = client.get("/?robot=pr2-sample").text
    assert body.count('class="scene"') == 1
    middle = sorted(week.scenes, key=lambda s: s.timestamp)[10:15]
    since = kitchen_week_time(middle[0].timestamp)
    until = kitchen_week_time(middle[-1].timestamp)
    body = client.get("/", params={"since": since, "until": until}).text
    shown = re.findall(r'data-scene="([0-9a-f]{24})"', body)
    assert shown == [str(s.id) for s in reversed(middle)]


def kitchen_week_time(stamp: int) -> str:
    """The ISO form of a timestamp the filter form sends (microseconds are enough here)."""
    from datetime import UTC, datetime

    return datetime.fromtimestamp(stamp / 1e9, UTC).replace(tzinfo=None).isoformat()
