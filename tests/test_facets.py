"""Facet counts on the scene log (webui/facets.py): each value's count is the number of scenes
it selects with the other filters, read from an index (never a collection scan), capped."""

from __future__ import annotations

import re

import pytest
from fastapi.testclient import TestClient

from percept_memory.demo import kitchen_week
from percept_memory.memory.settings import Settings
from percept_memory.queries.engine import QueryEngine
from percept_memory.queries.model import ClusterQuery
from percept_memory.webui import facets
from percept_memory.webui.app import create_app
from percept_memory.webui.scene_log import CHOICES, scene_filter

from .conftest import LOCAL, ingest_consolidated


@pytest.fixture(scope="module")
def memory(store):
    scenes = kitchen_week.generate(days=1).scenes
    for scene in scenes[::3]:
        scene.robot = "tiago"  # a second robot, with scenes of every region
    ingest_consolidated(store, scenes)
    return store


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
    counts = facets.facet_counts(memory.scenes, {}, choices_of(memory), CHOICES)
    assert all(n is None for values in counts.values() for n in values.values())
    client = TestClient(create_app(memory, Settings(consolidator=False)), base_url=LOCAL)
    assert '<option value="tiago">tiago</option>' in client.get("/scenes").text


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
