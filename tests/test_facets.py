"""Facet counts on the scene log and the search page (webui/facets.py): each value's count is
the number of scenes or clusters it selects with the other filters, read from an index (never
a collection scan), capped; and the scene log's histogram over time (webui/histogram.py)."""

from __future__ import annotations

import re
from contextlib import contextmanager
from urllib.parse import parse_qsl, urlsplit

import pytest
from bson import ObjectId
from fastapi.testclient import TestClient
from playwright.sync_api import expect

from percept_memory.demo import kitchen_week
from percept_memory.memory.settings import Settings
from percept_memory.memory.types import timestamp_from_iso
from percept_memory.queries.engine import QueryEngine
from percept_memory.queries.model import ClusterQuery
from percept_memory.webui import facets, histogram
from percept_memory.webui.app import create_app
from percept_memory.webui.scene_log import CHOICES, scene_filter

from .conftest import LOCAL, ingest_consolidated
from .test_webui import SCREENSHOTS
from .test_webui_curation import in_chromium


@pytest.fixture(scope="module")
def memory(store):
    scenes = kitchen_week.generate(days=1).scenes
    for scene in scenes[::3]:
        scene.robot = "tiago"  # a second robot, with scenes of every region
    ingest_consolidated(store, scenes)
    return store


@pytest.fixture(autouse=True)
def time_to_count(monkeypatch):
    """Counts are checked here, not the page's time budget (but where a test sets it): a
    machine busy with other tests must not leave a count out."""
    monkeypatch.setattr(facets, "BUDGET_MS", 10_000)
    monkeypatch.setattr(facets, "SEARCH_BUDGET_MS", 10_000)


def choices_of(store) -> dict[str, list[str]]:
    return {name: sorted(v for v in store.scenes.distinct(key) if v is not None)
            for name, key in CHOICES.items()}


@pytest.mark.parametrize("filters", [
    {},
    {"robot": "tiago"},
    {"robot": "tiago", "since": "2024-03-04T12:00"},
    {"region": "table", "annotator": "OCRAnnotator"},
])
def test_each_count_is_what_choosing_that_value_would_select(memory, filters):
    given = {name: filters.get(name, "") for name in (*CHOICES, "since", "until")}
    choices = choices_of(memory)
    query = scene_filter(given, choices["type"])
    counts = facets.facet_counts(memory.scenes, query, choices, CHOICES)
    assert set(counts) == set(CHOICES)
    for name, values in choices.items():
        for value in values:
            chosen = scene_filter({**given, name: value}, choices["type"])
            assert counts[name][value] == memory.scenes.count_documents(chosen), (name, value)
    assert counts["robot"]["tiago"] > 0


def plan_stages(plan: dict) -> set[str]:
    stages = {plan.get("stage")}
    for key in ("inputStage", "inputStages"):
        children = plan.get(key, [])
        for child in children if isinstance(children, list) else [children]:
            stages |= plan_stages(child)
    return stages


@pytest.mark.parametrize("query", [
    {"robot": "tiago"},
    {"summary.regions": "table"},
    {"summary.annotators": "OCRAnnotator", "timestamp": {"$gte": 0}},
    {"summary.types": "pm.annotation.Shape", "robot": "tiago"},
])
def test_a_count_reads_an_index_not_the_collection(memory, query):
    explained = memory.db.command("explain", {"aggregate": "scenes", "pipeline": [
        {"$match": query}, {"$limit": facets.CAP + 1}, {"$group": {"_id": 1, "n": {"$sum": 1}}}],
        "cursor": {}}, verbosity="queryPlanner")
    winning = explained.get("queryPlanner") or explained["stages"][0]["$cursor"]["queryPlanner"]
    stages = plan_stages(winning["winningPlan"])
    assert "COLLSCAN" not in stages and stages & {"IXSCAN", "COUNT_SCAN"}, stages


def test_counts_stop_at_the_cap(memory, monkeypatch):
    monkeypatch.setattr(facets, "CAP", 5)
    choices = choices_of(memory)
    counts = facets.facet_counts(memory.scenes, {}, choices, CHOICES)
    assert counts["robot"]["tiago"] == 6 and facets.shown(6) == "5+"
    assert facets.shown(3) == "3" and facets.shown(None) == ""


def test_the_scene_log_shows_the_counts_beside_the_values(memory):
    client = TestClient(create_app(memory, Settings(consolidator=False)), base_url=LOCAL)
    text = client.get("/scenes", params={"region": "table"}).text
    tiago = memory.scenes.count_documents({"robot": "tiago", "summary.regions": "table"})
    assert re.search(rf'<option value="tiago">tiago \({tiago}\)</option>', text)
    everywhere = memory.scenes.count_documents({})
    region = re.search(r'<option value="table" selected>table \((\d+)\)</option>', text)
    assert int(region[1]) == memory.scenes.count_documents({"summary.regions": "table"})
    assert int(region[1]) < everywhere


def test_counts_left_when_the_time_budget_runs_out_show_no_number(memory, monkeypatch):
    monkeypatch.setattr(facets, "BUDGET_MS", 0)
    monkeypatch.setattr(facets, "SEARCH_BUDGET_MS", 0)
    counts = facets.facet_counts(memory.scenes, {}, choices_of(memory), CHOICES)
    assert all(n is None for values in counts.values() for n in values.values())
    client = TestClient(create_app(memory, Settings(consolidator=False)), base_url=LOCAL)
    assert '<option value="tiago">tiago</option>' in client.get("/scenes").text
    searched = client.get("/search", params={"text": "cup"}).text
    assert '<option value="tiago">tiago</option>' in searched
    assert re.search(r"\d+ of the values offered show no count", searched)
    monkeypatch.undo()  # with the time to count
    assert "show no count" not in client.get("/search").text


@pytest.mark.parametrize("asked", [{}, {"text": "cup"}, {"text": "cup", "robot": "tiago"},
                                   {"region": ["table", "shelf"]}])
def test_the_search_page_counts_each_region_and_robot_with_the_rest_of_the_query(memory,
                                                                                  asked):
    engine = QueryEngine(memory)
    choices = {"region": sorted(memory.clusters.distinct("search.region")),
               "robot": sorted(memory.clusters.distinct("search.robot"))}
    counts = facets.cluster_facet_counts(engine.runner, memory.clusters,
                                         ClusterQuery(**asked), choices)
    for name, values in choices.items():
        for value in values:
            expected = engine.clusters(**{**asked, name: [value], "limit": 0, "count": True}).total
            assert counts[name][value] == min(expected, facets.CAP + 1), (name, value)
    client = TestClient(create_app(memory, Settings(consolidator=False)), base_url=LOCAL)
    text = client.get("/search", params={**asked}).text
    table = counts["region"]["table"]
    assert f'table ({facets.shown(table)})</option>' in text or table == 0


@pytest.mark.parametrize("asked", [{}, {"text": "cup"}, {"region": ["table"]},
                                   {"labelled": ["Cup"]}, {"sphere": "1.9,4.6,0.8,1.5"}])
@pytest.mark.parametrize("looked", [3, 1000])
def test_the_most_frequent_labels_and_objects_are_offered_with_their_counts(memory, monkeypatch,
                                                                         asked, looked):
    """A look at few matches finds the values to offer, and they are counted all the same."""
    monkeypatch.setattr(facets, "LOOKED", looked)
    engine = QueryEngine(memory)
    counts = facets.cluster_facet_counts(engine.runner, memory.clusters, ClusterQuery(**asked),
                                         {"region": [], "robot": []})
    for name in facets.FREQUENT:
        assert 0 < len(counts[name]) <= facets.TOP + len(asked.get(name, [])), name
        for value, count in counts[name].items():
            expected = engine.clusters(**{**asked, name: [value], "limit": 0,
                                          "count": True}).total
            assert count == min(expected, facets.CAP + 1) and count > 0, (name, value)
    if looked == 1000:  # all the matches looked at: the others offered are the most frequent
        labels = [n for value, n in counts["labelled"].items() if value != "cup"]
        assert labels == sorted(labels, reverse=True)
    if asked.get("labelled"):
        assert "cup" in counts["labelled"]  # a chosen value is offered, to be taken out


def test_a_label_seen_over_the_cap_in_a_short_look_needs_no_count_of_its_own(memory,
                                                                            monkeypatch):
    """Over CAP among the matches looked at, it is over CAP among them all: "CAP+" as if
    counted, when counting gets no time."""
    monkeypatch.setattr(facets, "CAP", 3)
    monkeypatch.setattr(facets, "LOOKED", 20)
    monkeypatch.setattr(facets, "counts_of", lambda collection, queries, *_: [None] * len(queries))
    engine = QueryEngine(memory)
    counts = facets.cluster_facet_counts(engine.runner, memory.clusters, ClusterQuery(),
                                         {"region": [], "robot": []})
    settled = {value: n for value, n in counts["labelled"].items() if n is not None}
    assert settled and set(settled.values()) == {4}
    for value in settled:
        assert engine.clusters(labelled=[value], limit=0, count=True).total > 3
    assert None in counts["labelled"].values()  # those seen fewer times still need a count


def test_a_label_or_an_object_offered_narrows_the_search_by_keyboard_and_back(memory):
    with in_chromium(memory) as (tab, url):
        tab.goto(f"{url}/search?text=cup")
        everything = int(tab.locator("p.summary").inner_text().split()[0])
        label = tab.locator("#facet-labelled + ul a").first
        name = label.inner_text()
        label.focus()
        with tab.expect_navigation():
            tab.keyboard.press("Enter")
        given = parse_qsl(urlsplit(tab.url).query)
        assert ("text", "cup") in given and ("labelled", name) in given
        narrowed = int(tab.locator("p.summary").inner_text().split()[0])
        assert 0 < narrowed <= everything
        assert narrowed == QueryEngine(memory).clusters(
            text="cup", labelled=[name], limit=0, count=True).total
        chosen = tab.locator("#facet-labelled + ul li.chosen a")
        expect(chosen).to_have_text(name)
        SCREENSHOTS.mkdir(parents=True, exist_ok=True)
        tab.screenshot(path=str(SCREENSHOTS / "search-facets.png"))  # the form, facets, hits
        objects = tab.locator("#facet-object + ul a")
        expect(objects.first).to_be_visible()
        with tab.expect_navigation():
            chosen.click()  # taken out again
        assert dict(parse_qsl(urlsplit(tab.url).query)) == {"text": "cup", "view": "grid"}
        with tab.expect_navigation():
            tab.locator("#facet-object + ul a").first.click()
        only = dict(parse_qsl(urlsplit(tab.url).query))["object"]
        assert {h["object_id"] for h in memory.clusters.find(
            {"_id": {"$in": [ObjectId(tab.locator("li.hit").nth(i).get_attribute(
                "data-cluster")) for i in range(tab.locator("li.hit").count())]}})} == {
            ObjectId(only)}


SPHERE = "1.9,4.6,0.8,1.5"


@pytest.mark.parametrize("few", [0, 3])  # the 3 robots counted one by one first, or grouped too
@pytest.mark.parametrize("grouped", [1, 60, 5000])
@pytest.mark.parametrize("asked", [{}, {"text": "cup"}, {"sphere": SPHERE},
                                   {"sphere": SPHERE, "robot": ["tiago"]},
                                   {"sphere": SPHERE, "region": ["table", "shelf"]},
                                   {"where": ["shape:shape=box"], "robot": ["nobody"]}])
def test_a_first_look_that_settles_some_counts_leaves_the_rest_to_be_counted(
        memory, monkeypatch, grouped, asked, few):
    """The first look groups by region and robot at once: a region's count keeps only the
    groups of the robots asked for, and a robot's those of the regions asked for."""
    monkeypatch.setattr(facets, "CAP", 5)
    monkeypatch.setattr(facets, "GROUPED", grouped)
    monkeypatch.setattr(facets, "FEW", few)
    engine = QueryEngine(memory)
    choices = {"region": sorted(memory.clusters.distinct("search.region")),
               "robot": ["nobody", *sorted(memory.clusters.distinct("search.robot"))]}
    counts = facets.cluster_facet_counts(engine.runner, memory.clusters, ClusterQuery(**asked),
                                         choices)
    for name, values in choices.items():
        for value in values:
            expected = engine.clusters(**{**asked, name: [value], "limit": 0,
                                          "count": True}).total
            assert counts[name][value] == min(expected, 6), (name, value, grouped)
    assert any(n for values in counts.values() for n in values.values())


@pytest.mark.parametrize("field", ["search.region", "search.robot"])
@pytest.mark.parametrize("words", [["cup"], ["cup", "plate"]])
def test_a_text_is_counted_by_region_and_robot_from_index_keys_alone(memory, field, words):
    value = sorted(memory.clusters.distinct(field))[0]
    explained = memory.db.command("explain", {"aggregate": "clusters", "pipeline": [
        {"$match": {"search.terms": {"$in": words}, field: value}},
        {"$limit": facets.CAP + 1}, {"$group": {"_id": 1, "n": {"$sum": 1}}}],
        "cursor": {}}, verbosity="executionStats")
    found = explained.get("executionStats") or explained["stages"][0]["$cursor"][
        "executionStats"]
    assert found["nReturned"] > 0 and found["totalDocsExamined"] == 0, found


# --- the histogram of scenes over time (webui/histogram.py) ----------------------------------


@pytest.mark.parametrize("filters", [{}, {"robot": "tiago"}, {"region": "table"}])
def test_the_histogram_counts_every_selected_scene_once(memory, filters):
    given = {name: filters.get(name, "") for name in (*CHOICES, "since", "until")}
    query = scene_filter(given, choices_of(memory)["type"])
    drawn = histogram.scene_histogram(memory.scenes, query)
    assert len(drawn.bars) == histogram.BARS
    assert sum(bar.scenes for bar in drawn.bars) == memory.scenes.count_documents(query)
    for bar, after in zip(drawn.bars, drawn.bars[1:], strict=False):
        assert bar.end == after.start and 0 <= bar.height <= drawn.height
    assert max(bar.height for bar in drawn.bars) == drawn.height
    for bar in drawn.bars:  # its link selects what it counts
        linked = scene_filter({**given, "since": bar.since, "until": bar.until},
                              choices_of(memory)["type"])
        assert memory.scenes.count_documents(linked) == bar.scenes


def test_until_is_through_the_precision_it_is_written_in_and_a_type_shows_chosen(memory):
    """`until` a minute, a second or a millisecond takes in all of it, as a form's time field
    (minutes or seconds) means it; nanoseconds are exact. A type named by its short name is
    shown chosen, so the form keeps it."""
    stamp = memory.scenes.find_one({}, sort=[("timestamp", -1)])["timestamp"]
    types = choices_of(memory)["type"]
    moment = histogram._iso(stamp)  # to the millisecond, below the stamp's own digits
    for until in (moment[:16], moment[:19], moment, str(stamp)):
        query = scene_filter({**dict.fromkeys((*CHOICES, "since"), ""), "until": until}, types)
        assert memory.scenes.count_documents(query) == memory.scenes.count_documents({}), until
    client = TestClient(create_app(memory, Settings(consolidator=False)), base_url=LOCAL)
    shown = client.get("/scenes", params={"type": "Logo"}).text
    assert '<option value="pm.annotation.Logo" selected>' in shown


def test_no_scenes_no_histogram(memory):
    assert histogram.scene_histogram(memory.scenes, {"robot": "nobody"}) is None


def test_a_histogram_not_counted_in_time_is_left_out(memory, monkeypatch):
    assert histogram.scene_histogram(memory.scenes, {}) is not None
    monkeypatch.setattr(histogram, "BUDGET_MS", 0)
    assert histogram.scene_histogram(memory.scenes, {}) is None
    client = TestClient(create_app(memory, Settings(consolidator=False)), base_url=LOCAL)
    page = client.get("/scenes")
    assert page.status_code == 200 and "figure class=\"histogram\"" not in page.text


@contextmanager
def tiagos_scene_log(memory):
    """Robot tiago's scene log in Chromium with its histogram's bars drawn (tab, bars); the
    page must keep its own Content-Security-Policy."""
    with in_chromium(memory) as (tab, url):
        tab.goto(f"{url}/scenes?robot=tiago")
        bars = tab.locator("figure.histogram a.bar")
        expect(bars).to_have_count(histogram.BARS)
        yield tab, bars


def test_a_bar_of_the_histogram_sets_the_time_range_by_keyboard(memory):
    with tiagos_scene_log(memory) as (tab, bars):
        fullest = max(range(histogram.BARS), key=lambda i: int(
            bars.nth(i).get_attribute("aria-label").split()[0]))
        scenes = int(bars.nth(fullest).get_attribute("aria-label").split()[0])
        bars.nth(fullest).focus()
        SCREENSHOTS.mkdir(parents=True, exist_ok=True)
        tab.locator("figure.histogram").screenshot(path=str(SCREENSHOTS / "histogram.png"))
        with tab.expect_navigation():
            tab.keyboard.press("Enter")
        assert "robot=tiago" in tab.url and "since=" in tab.url and "until=" in tab.url
        expect(tab.locator("table.scenes tbody tr")).to_have_count(min(scenes, 20))
        linked = dict(parse_qsl(urlsplit(tab.url).query))
        for name in ("since", "until"):  # the form's time fields take the bar's times...
            given = tab.locator(f"input[name={name}]").input_value()
            assert timestamp_from_iso(given) == timestamp_from_iso(linked[name])
        with tab.expect_navigation():
            tab.locator("form.filters button[type=submit]").click()  # ...and keep them
        again = dict(parse_qsl(urlsplit(tab.url).query))
        for name in ("since", "until"):
            assert timestamp_from_iso(again[name]) == timestamp_from_iso(linked[name])
        expect(tab.locator("table.scenes tbody tr")).to_have_count(min(scenes, 20))


@pytest.mark.parametrize("leftwards", [False, True])
def test_dragging_across_the_bars_sets_the_time_range_to_them(memory, leftwards):
    with tiagos_scene_log(memory) as (tab, bars):
        low, high = 3, 9
        spans = [dict(parse_qsl(urlsplit(bars.nth(i).get_attribute("href")).query))
                 for i in (low, high)]
        scenes = sum(int(bars.nth(i).get_attribute("aria-label").split()[0])
                     for i in range(low, high + 1))
        start, end = (bars.nth(i).locator("rect.hit").bounding_box() for i in (low, high))
        if leftwards:
            start, end = end, start
        tab.mouse.move(start["x"] + start["width"] / 2, start["y"] + 10)
        tab.mouse.down()
        tab.mouse.move(end["x"] + end["width"] / 2, end["y"] + 10, steps=8)
        expect(tab.locator("figure.histogram a.bar.brushed")).to_have_count(high - low + 1)
        if not leftwards:
            tab.locator("figure.histogram").screenshot(
                path=str(SCREENSHOTS / "histogram-brush.png"))
        with tab.expect_navigation():
            tab.mouse.up()
        given = dict(parse_qsl(urlsplit(tab.url).query))
        assert given == {"robot": "tiago", "since": spans[0]["since"],
                         "until": spans[1]["until"]}
        query = scene_filter({**dict.fromkeys((*CHOICES, "since", "until"), ""), **given},
                             choices_of(memory)["type"])
        assert memory.scenes.count_documents(query) == scenes
        expect(tab.locator("table.scenes tbody tr")).to_have_count(min(scenes, 20))


def test_a_click_on_one_bar_still_follows_its_link(memory):
    with in_chromium(memory) as (tab, url):
        tab.goto(f"{url}/scenes?robot=tiago")
        bar = tab.locator("figure.histogram a.bar").nth(5)
        href = bar.get_attribute("href")
        with tab.expect_navigation():
            bar.locator("rect.hit").click()
        assert tab.url == url + href
