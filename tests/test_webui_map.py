"""The map page at any density (issue 17, part 5): a map of thousands of objects is drawn with a
bounded number of items, the objects of dense cells counted in markers that lead to their part
of the map (`box=x0,y0,x1,y1`), sparse ones one by one with labels that never overlap; a
zoomed view asks only for its box, by index; bad boxes get a page naming the problem.

The dense map is written straight into `objects` and `events`, as consolidation leaves them
(memory/consolidation.py), beside the kitchen day of test_webui (consolidated): three clumps
of objects, objects alone on the floor, some hidden, and one moved out of its clump.
"""

from __future__ import annotations

import re
from urllib.parse import parse_qs, urlencode, urlparse

import numpy as np
import pytest
from bson import ObjectId
from playwright.sync_api import expect

from percept_memory.demo import kitchen_week
from percept_memory.memory.schema import EVENTS, MAPS, OBJECTS
from percept_memory.memory.types import Scene
from percept_memory.webui import belief_map

from . import test_webui
from .conftest import ingest_consolidated
from .test_webui import NO_ALT, TABBABLE, TEXT_BOXES, UNLABELLED, overlapping, shot

browser, page, url, client = test_webui.browser, test_webui.page, test_webui.url, test_webui.client

MAP = "warehouse"
SECOND = 10**9
T0 = 1_700_000_000 * SECOND
HOUR = 3600 * SECOND
CLUMPS = {"a": (2.0, 3.0), "b": (8.0, 1.0), "c": (5.0, 6.0)}  # 0.3 m squares
PER_CLUMP, ALONE = 1000, 30
AWAY = (9.5, 7.5)  # where the wanderer went, out of clump a, at T0 + 2 h
MOST_DRAWN = max(belief_map.ONE_BY_ONE, belief_map.SPARSE * (
    belief_map.WIDTH // belief_map.CELL + 1) * (belief_map.MAX_HEIGHT // belief_map.CELL + 1))


@pytest.fixture(scope="module")
def dense(store) -> dict:
    """The warehouse: per object its position now, and the wanderer's id."""
    rng = np.random.default_rng(17)
    places = [(c, [round(v + rng.uniform(0, 0.3), 4) for v in spot] + [0.9])
              for c, spot in CLUMPS.items() for _ in range(PER_CLUMP)]
    places += [("floor", [round(rng.uniform(0, 10), 4), round(rng.uniform(0, 8), 4), 0.0])
               for _ in range(ALONE)]
    objects, events, now = [], [], {}
    for i, (region, position) in enumerate(places):
        object_id = ObjectId()
        hidden = region == "b" and i % 2 == 0  # half of clump b is out of view
        events.append(_event(object_id, T0 + i * SECOND, "appear", position, region))
        if hidden:
            events.append(_event(object_id, T0 + HOUR, "hidden", position, region))
        now[object_id] = position
        objects.append({"_id": object_id, "map": MAP, "name": f"{region} box {i}",
                        "names": [f"{region} box {i}"], "state": "hidden" if hidden else "present",
                        "first_seen": T0 + i * SECOND, "last_seen": T0 + i * SECOND,
                        "position": position, "x": position[0], "y": position[1],
                        "region": region, "robot": "forklift", "observations": 1})
    wanderer = objects[0]["_id"]  # of clump a
    now[wanderer] = [*AWAY, 0.0]
    events.append(_event(wanderer, T0 + 2 * HOUR, "move", now[wanderer], "floor"))
    objects[0].update(position=now[wanderer], x=AWAY[0], y=AWAY[1], region="floor")
    store.db[OBJECTS].insert_many(objects)
    store.db[EVENTS].insert_many(events)
    scenes = [Scene(timestamp=T0 + k * HOUR, robot="forklift", map=MAP) for k in (0, 3)]
    store.put_scenes(scenes)
    store.outbox.delete_many({"_id": {"$in": [s.id for s in scenes]}})  # the belief is given
    store.db[MAPS].update_one({"_id": MAP}, {"$set": {"consolidated": None}}, upsert=True)
    return {"now": now, "wanderer": wanderer}


def _event(object_id, t, explanation, position, region) -> dict:
    return {"map": MAP, "object_id": object_id, "scene_id": ObjectId(), "cluster_id": None,
            "time": t, "robot": "forklift", "explanation": explanation, "probability": 0.9,
            "alternatives": [], "position": position, "region": region}


@pytest.fixture(scope="module")
def filled(store, dense):
    ingest_consolidated(store, kitchen_week.generate(days=1).scenes)
    return store


def drawn(page) -> tuple[int, int, int]:
    """Objects drawn one by one, markers, and the objects the markers count."""
    counts = page.locator("a.marker").evaluate_all("ms => ms.map(m => Number(m.dataset.count))")
    return page.locator("a.object").count(), len(counts), sum(counts)


def test_a_dense_map_draws_a_bounded_number_of_items_counting_every_object(page, url, dense):
    page.goto(f"{url}/map?map={MAP}")
    single, markers, counted = drawn(page)
    assert single + markers <= MOST_DRAWN and markers >= 3
    assert single + counted == len(dense["now"])  # every object believed now, once
    assert overlapping(page.locator("figure.map svg").evaluate(TEXT_BOXES)) == []
    labelled = page.locator("a.object text").count()
    crowded = sum(int(t.removeprefix("+")) for t in
                  page.locator("g.crowd text").all_text_contents())
    assert labelled + crowded == single and labelled > 0
    assert page.locator("table.believed tbody tr").count() == single + markers
    shot(page, "17-map-dense")


def test_markers_are_named_links_in_the_tab_order(page, url, dense):
    page.goto(f"{url}/map?map={MAP}")
    assert page.evaluate(NO_ALT) == [] and page.evaluate(UNLABELLED) == []
    page.evaluate(TABBABLE)  # numbers what Tab visits
    markers = page.locator("a.marker")
    for i in range(markers.count()):
        marker = markers.nth(i)
        assert marker.get_attribute("data-audit") is not None
        count = marker.get_attribute("data-count")
        expect(marker).to_have_accessible_name(
            re.compile(rf"^{count} objects, \d+ seen there, \d+ hidden: zoom in$"))
    markers.first.focus()
    page.keyboard.press("Enter")
    expect(page).to_have_url(re.compile(r"box="))


def test_a_map_whose_scenes_are_not_consolidated_yet_has_its_page(client, store):
    """Its first scenes are stored before the consolidator makes its belief: the page was a
    404 "no map named" meanwhile."""
    (ids,) = store.put_scenes([Scene(timestamp=1_000, robot="r", map="just-started")])
    try:
        answer = client.get("/map", params={"map": "just-started"})
        assert answer.status_code == 200 and "just-started" in answer.text
    finally:
        store.scenes.delete_one({"_id": ids.scene_id})
        store.db["outbox"].delete_one({"_id": ids.scene_id})


def test_a_sparse_map_draws_each_object(client):
    body = client.get("/map", params={"map": kitchen_week.MAP}).text
    assert 'class="marker' not in body and body.count('class="object ') > 10


def test_zooming_into_a_marker_shows_its_objects(page, url, dense):
    page.goto(f"{url}/map?map={MAP}")
    biggest = max(page.locator("a.marker").all(), key=lambda m: int(m.get_attribute("data-count")))
    count = int(biggest.get_attribute("data-count"))
    biggest.locator("circle").click()
    expect(page).to_have_url(re.compile(r"box="))
    box = belief_map.MapBox.parse(parse_qs(urlparse(page.url).query)["box"][0])
    inside = [o for o, p in dense["now"].items() if box.holds(p)]
    single, markers, counted = drawn(page)
    assert single + counted == len(inside) >= count
    assert single + markers <= MOST_DRAWN
    assert overlapping(page.locator("figure.map svg").evaluate(TEXT_BOXES)) == []
    while markers:  # down to the objects themselves
        page.locator("a.marker circle").first.click()
        single, markers, _ = drawn(page)
    shown = [ObjectId(o) for o in page.locator("a.object").evaluate_all(
        "os => os.map(o => o.dataset.object)")]
    box = belief_map.MapBox.parse(parse_qs(urlparse(page.url).query)["box"][0])
    assert sorted(shown) == sorted(o for o, p in dense["now"].items() if box.holds(p))
    expect(page.locator("a.object text").first).to_be_visible()
    page.get_by_role("link", name="whole map").click()
    expect(page).to_have_url(f"{url}/map?map={MAP}")


def test_a_zoomed_past_moment_shows_what_was_there_then(client, dense):
    """The wanderer left clump a at T0 + 2 h: zoomed into clump a, it is counted an hour
    before, not now; zoomed to where it went, the other way round."""
    clump = {"map": MAP, "box": "1.9,2.9,2.4,3.4"}
    away = {"map": MAP, "box": ",".join(str(v) for v in (AWAY[0] - 0.01, AWAY[1] - 0.01,
                                                          AWAY[0] + 0.01, AWAY[1] + 0.01))}
    wanderer = f'data-object="{dense["wanderer"]}"'

    def objects(query: dict) -> int:
        body = client.get("/map?" + urlencode(query)).text
        return body.count('class="object ') + sum(
            int(n) for n in re.findall(r'class="marker[^"]*" data-count="(\d+)"', body))

    before = {"at": (T0 + HOUR) // SECOND}
    assert objects(clump | before) == PER_CLUMP and objects(clump) == PER_CLUMP - 1
    assert wanderer in client.get("/map?" + urlencode(away)).text
    assert objects(away) == 1 and objects(away | before) == 0
    past = client.get("/map?" + urlencode({"map": MAP} | before)).text
    links = re.findall(r'<a href="([^"]+)" class="marker', past)  # keep the moment
    assert links and all(f"&amp;t={T0 + HOUR}&amp;box=" in link for link in links)


def test_the_map_reads_by_index_alone(client, store, dense):
    store.client.admin.command("setParameter", 1, notablescan=True)
    try:
        for query in ({"map": MAP}, {"map": MAP, "box": "1.9,2.9,2.4,3.4"},
                      {"map": MAP, "box": "1.9,2.9,2.4,3.4", "at": (T0 + HOUR) // SECOND}):
            assert client.get("/map?" + urlencode(query)).status_code == 200, query
    finally:
        store.client.admin.command("setParameter", 1, notablescan=False)


def test_the_zoom_needs_no_script(client, dense):
    response = client.get("/map?" + urlencode({"map": MAP, "box": "0,0,5,5"}))
    assert "script-src" not in response.headers["content-security-policy"]
    assert "<script" not in response.text
    assert '<a href="/map?map=warehouse">whole map</a>' in response.text
    wider = "/map?map=warehouse&amp;box=-2.5%2C-2.5%2C7.5%2C7.5"
    assert f'<a href="{wider}">zoom out</a>' in response.text


@pytest.mark.parametrize("box", [
    "1,2,3", "1,2,3,4,5", "a,b,c,d", "", " ", "1,1,0,2", "0,0,0,0", "nan,0,1,1", "0,0,inf,1",
    "1e309,0,1,1", "$gt,0,1,1", "9" * 400 + ",0,1,1", "0,0,1,1\x00",
])
def test_a_bad_box_gets_a_page_naming_the_problem(client, dense, box):
    response = client.get("/map", params={"map": MAP, "box": box})
    if box == "":
        assert response.status_code == 200  # no box: the whole map
        return
    assert response.status_code == 422, response.text
    assert response.headers["content-type"].startswith("text/html")
    assert 'role="alert"' in response.text and "box" in response.text


@pytest.mark.parametrize("box", ["1,2,3", "0,0,0,1,1", "1,1,1,0,0,0", "nan,0,0,1,1,1"])
def test_the_api_answers_a_bad_box_with_its_error_shape(client, dense, box):
    response = client.get("/api/what-is-at", params={"map": MAP, "box": box})
    assert response.status_code == 422
    assert response.json()["error"]["status"] == 422


def test_cells_bound_what_is_drawn_however_many_points():
    rng = np.random.default_rng(3)
    points = [(x, y, i) for i, (x, y) in enumerate(rng.uniform(0, [960, 720], (100_000, 2)))]
    single, dense = belief_map.gather(points, belief_map.CELL, belief_map.SPARSE)
    assert len(single) + len(dense) <= MOST_DRAWN
    assert len(single) + sum(map(len, dense)) == len(points)
