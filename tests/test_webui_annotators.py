"""The annotators page and its API on data whose numbers are worked out by hand: six scenes of
a robot `lab` over three of four hours, two annotators logging known times, warnings and
errors, and twelve clusters classified by an SVM, named by a detector and labelled with a
ground truth; beside a day of the kitchen week (robot pr2) and the real RoboSherlock store
with its ground truth. The charts and tables are checked in a real headless Chromium."""

from __future__ import annotations

import re
from datetime import UTC, datetime
from pathlib import Path
from urllib.parse import parse_qsl, urlsplit

import pytest
from fastapi.testclient import TestClient
from playwright.sync_api import sync_playwright

from percept_memory.demo import kitchen_week
from percept_memory.ingest import robosherlock
from percept_memory.memory.settings import Settings
from percept_memory.memory.types import (
    Classification,
    Cluster,
    Detection,
    GroundTruth,
    LogLine,
    Scene,
    timestamp_from_datetime,
)
from percept_memory.queries.annotators import GROUND_TRUTH
from percept_memory.queries.engine import QueryEngine
from percept_memory.webui.app import create_app

from .conftest import LOCAL, ROBOSHERLOCK, served
from .test_webui import CHROMIUM
from .test_webui_curation import launch, watched

DOCS = Path(__file__).resolve().parents[1] / "docs" / "screenshots"
HOUR = 3600 * 10**9
EIGHT = timestamp_from_datetime(datetime(2024, 3, 4, 8, tzinfo=UTC))  # the kitchen's first day
MINUTES = [10, 40, 65, 80, 110, 210]  # after 8:00: two scenes at 8, three at 9, one at 11
# per cluster, two a scene: (ground truth, SVM's class, detector's name); None: not given
VERDICTS = [("cup", "cup", "cup"), ("cup", "cup", "cup"), ("cup", "bowl", "cup"),
            ("cup", "bowl", "cup"), ("bowl", "bowl", "plate"), ("plate", None, "plate"),
            (None, "cup", "bowl"), ("cup", "cup", "cup"), ("bowl", "bowl", "bowl"),
            ("plate", "plate", "plate"), (None, None, "cup"), ("bowl", "cup", None)]
# Flaky's lines per scene: a run, a warning, an error
FLAKY = [("run", "warning"), ("run",), ("run", "warning", "error"), ("run", "error"), ("run",),
         ("error",)]


def lab_scenes() -> list[Scene]:
    scenes = []
    for i, minutes in enumerate(MINUTES):
        clusters = []
        for truth, svm, decaf in VERDICTS[2 * i:2 * i + 2]:
            annotations = []
            if truth:
                annotations.append(GroundTruth(class_name=truth))
            if svm:
                annotations.append(Classification(source="SVM", class_name=svm))
            if decaf:
                annotations.append(Detection(source="DeCaf", name=decaf))
            clusters.append(Cluster(annotations=annotations))
        log = [LogLine(source="Fast", message="done", duration_ms=10.0 * (i + 1))]
        log += [LogLine(source="Flaky", message="ran", duration_ms=100.0) if what == "run" else
                LogLine(source="Flaky", level=what, message=f"Flaky {what} in scene {i}")
                for what in FLAKY[i]]
        scenes.append(Scene(timestamp=EIGHT + minutes * 60 * 10**9, robot="lab",
                            clusters=clusters, log=log))
    return scenes


@pytest.fixture(scope="module")
def lab(store):
    scenes = lab_scenes()
    store.put_scenes(scenes)
    store.put_scenes(kitchen_week.generate(days=1).scenes)
    return scenes


@pytest.fixture(scope="module")
def client(store, lab):
    return TestClient(create_app(store, Settings(consolidator=False)), base_url=LOCAL)


def report(client, **params) -> dict:
    answer = client.get("/api/annotators", params={"robot": "lab", **params})
    assert answer.status_code == 200, answer.text
    return answer.json()


def comparison(answer: dict, annotator: str, reference: str) -> dict:
    (found,) = [c for c in answer["comparisons"]
                if (c["annotator"], c["reference"]) == (annotator, reference)]
    return found


# --- the API ------------------------------------------------------------------------------


def test_times_per_hour_are_the_hours_median_and_95th_percentile(client):
    hours = {(h["annotator"], (h["hour"] - EIGHT) // HOUR): h for h in report(client)["hours"]}
    assert {k for k in hours if k[0] == "Fast"} == {("Fast", 0), ("Fast", 1), ("Fast", 3)}
    assert (hours["Fast", 0]["p50_ms"], hours["Fast", 0]["p95_ms"]) == (15.0, 19.5)
    assert (hours["Fast", 1]["p50_ms"], hours["Fast", 1]["p95_ms"]) == (40.0, 49.0)
    assert (hours["Fast", 3]["runs"], hours["Fast", 3]["p95_ms"]) == (1, 60.0)
    flaky = {hour: (h["scenes"], h["runs"], h["warned"], h["failed"])
             for (name, hour), h in hours.items() if name == "Flaky"}
    assert flaky == {0: (2, 2, 1, 0), 1: (3, 3, 1, 2), 3: (1, 0, 0, 1)}
    assert hours["Flaky", 3]["p50_ms"] is None


def test_totals_and_the_latest_problems(client, lab):
    answer = report(client)
    assert (answer["scenes"], answer["first"], answer["last"]) == (
        6, lab[0].timestamp, lab[-1].timestamp)
    totals = {t["annotator"]: t for t in answer["annotators"]}
    assert (totals["Fast"]["runs"], totals["Fast"]["max_ms"]) == (6, 60.0)
    assert (totals["Flaky"]["warnings"], totals["Flaky"]["errors"]) == (2, 3)
    assert (totals["SVM"]["annotations"], totals["DeCaf"]["annotations"]) == (10, 11)
    assert [p["message"] for p in answer["problems"]] == [
        "Flaky error in scene 5", "Flaky error in scene 3", "Flaky warning in scene 2",
        "Flaky error in scene 2", "Flaky warning in scene 0"]


def test_the_confusion_against_the_ground_truth_with_precision_and_recall(client):
    svm = comparison(report(client), "SVM", GROUND_TRUTH)
    cells = {(c["said"], c["expected"]): c["clusters"] for c in svm["cells"]}
    assert cells == {("cup", "cup"): 3, ("bowl", "cup"): 2, ("bowl", "bowl"): 2,
                     (None, "plate"): 1, ("cup", None): 1, ("plate", "plate"): 1,
                     ("cup", "bowl"): 1}
    assert (svm["clusters"], svm["disagreements"]) == (11, 5)
    scores = {s["class_name"]: (s["precision"], round(s["recall"], 3), s["support"])
              for s in svm["scores"]}
    assert scores == {"cup": (0.75, 0.6, 5), "bowl": (0.5, 0.667, 3), "plate": (1.0, 0.5, 2)}


def test_a_class_is_compared_as_the_name_it_makes_and_a_cluster_counted_once(store):
    """SiggBottle, sigg bottle and Sigg_Bottle are one name (as naming and search have it), so
    no disagreement; an annotator that gave a cluster two classes counted it twice in the
    support of the reference's class (recall 15/21 for 15/20)."""
    def scene(i: int, robot: str, said: list[list[tuple[str, str]]]) -> Scene:
        return Scene(timestamp=EIGHT + i, robot=robot, clusters=[Cluster(annotations=[
            GroundTruth(class_name=truth), *(Classification(source=who, class_name=name)
                                             for who, name in given)])
            for truth, given in said])
    ids = store.put_scenes([
        scene(1, "spelt", [("SiggBottle", [("SVM", "sigg bottle"), ("YOLO", "Sigg_Bottle")])]),
        scene(2, "spelt", [("SiggBottle", [("SVM", "SiggBottle"), ("YOLO", "sigg bottle")])]),
        scene(3, "twice", [("cup", [("SVM", "cup"), ("SVM", "mug")]), ("cup", [("SVM", "cup")]),
                           ("cup", [("SVM", "cup")]), ("cup", [("SVM", "bowl")])])])
    try:
        compared_by_name(QueryEngine(store))
    finally:  # (the module's other tests read every robot's)
        store.scenes.delete_many({"_id": {"$in": [i.scene_id for i in ids]}})
        store.clusters.delete_many({"scene_id": {"$in": [i.scene_id for i in ids]}})


def compared_by_name(engine: QueryEngine) -> None:
    spelt = engine.annotator_report(robot="spelt").comparisons
    assert {(c.annotator, c.reference): c.disagreements for c in spelt} == {
        ("SVM", GROUND_TRUTH): 0, ("YOLO", GROUND_TRUTH): 0, ("SVM", "YOLO"): 0}
    (svm, *_) = spelt
    assert [(c.said, c.expected, c.clusters) for c in svm.cells] == [
        ("SiggBottle", "SiggBottle", 2)]  # (as it was most often spelt)
    cell = engine.annotator_clusters(robot="spelt", annotator="SVM", reference=GROUND_TRUTH,
                                     said="sigg_bottle", expected="sigg bottle")
    assert cell.total == 2
    (twice, *_) = engine.annotator_report(robot="twice").comparisons
    scores = {s.class_name: (s.precision, s.recall, s.support) for s in twice.scores}
    assert scores["cup"] == (1.0, 0.75, 4) and scores["mug"] == (0.0, None, 0)


def test_annotators_are_compared_with_each_other_too(client):
    answer = report(client)
    assert [(c["annotator"], c["reference"]) for c in answer["comparisons"]] == [
        ("SVM", GROUND_TRUTH), ("DeCaf", GROUND_TRUTH), ("DeCaf", "SVM")]
    pair = comparison(answer, "DeCaf", "SVM")
    cells = {(c["said"], c["expected"]): c["clusters"] for c in pair["cells"]}
    assert cells[("plate", "bowl")] == 1 and cells[("bowl", "cup")] == 1
    assert cells[("cup", None)] == 1 and cells[(None, "cup")] == 1
    assert pair["clusters"] == 12


def test_a_cell_lists_exactly_its_clusters_newest_first(client, lab):
    clusters = [c for scene in lab for c in scene.clusters]
    answer = client.get("/api/annotators/clusters", params={
        "robot": "lab", "annotator": "SVM", "reference": GROUND_TRUTH, "said": "bowl",
        "expected": "cup"})
    assert answer.status_code == 200, answer.text
    found = answer.json()
    assert found["total"] == 2
    assert [c["id"] for c in found["clusters"]] == [str(clusters[3].id), str(clusters[2].id)]
    assert found["clusters"][0]["verdicts"] == {GROUND_TRUTH: ["cup"], "DeCaf": ["cup"],
                                                "SVM": ["bowl"]}
    missed = client.get("/api/annotators/clusters", params={
        "robot": "lab", "annotator": "SVM", "reference": GROUND_TRUTH, "expected": "plate"})
    assert [c["id"] for c in missed.json()["clusters"]] == [str(clusters[5].id)]


def test_the_window_counts_scenes_up_to_a_moment(client):
    earlier = report(client, scenes=3, before=EIGHT + 90 * 60 * 10**9)
    assert earlier["scenes"] == 3 and (earlier["last"] - EIGHT) // 60 // 10**9 == 80
    assert {h["annotator"] for h in earlier["hours"]} == {"Fast", "Flaky"}
    # the page leads to the scenes before its window only when some may be (it led on from a
    # window that held the oldest scene, to an empty page)
    full = client.get("/annotators", params={"robot": "lab", "scenes": 3})
    assert 'rel="prev">the 3 before' in full.text
    oldest = client.get("/annotators", params={"robot": "lab", "scenes": 1000})
    assert oldest.status_code == 200 and 'rel="prev"' not in oldest.text


@pytest.mark.parametrize("query", [{"robot": "lab"}, {"scenes": 10, "before": EIGHT + HOUR}])
def test_every_read_of_the_report_and_its_cells_uses_an_index(store, lab, query):
    for name, extra in (("annotator_report", {}), ("annotator_clusters", {
            "annotator": "SVM", "reference": GROUND_TRUTH, "said": "cup"})):
        plans: list = []
        getattr(QueryEngine(store, explain=plans), name)(**query, **extra)
        assert plans
        for plan in plans:
            assert "COLLSCAN" not in plan["stages"] and plan["indexes"], plan


@pytest.mark.parametrize("path, params, problem", [
    ("/api/annotators", {"scenes": "0"}, "scenes"),
    ("/api/annotators", {"scenes": "5001"}, "scenes"),
    ("/api/annotators", {"scenes": "many"}, "scenes"),
    ("/api/annotators", {"before": "yesterday"}, "before"),
    ("/api/annotators", {"colour": "red"}, "colour"),
    ("/api/annotators", {"robot": ["a", "b"]}, "robot"),
    ("/api/annotators/clusters", {"annotator": "SVM", "said": "cup"}, "reference"),
    ("/api/annotators/clusters", {"annotator": "SVM", "reference": "SVM", "said": "cup"}, ""),
    ("/api/annotators/clusters", {"annotator": "SVM", "reference": "DeCaf"}, ""),
    ("/api/annotators/clusters", {"annotator": "SVM", "reference": "DeCaf", "said": "cup",
                                  "limit": "501"}, "limit"),
])
def test_bad_parameters_get_the_error_shape_naming_them(client, path, params, problem):
    for answer in (client.get(path, params=params),
                   client.post(path, json={k: v for k, v in params.items()})):
        assert answer.status_code == 422, answer.text
        error = answer.json()["error"]
        assert error["status"] == 422 and error["problems"]
        assert any(p["path"].removeprefix("body.").startswith(problem)
                   for p in error["problems"]), error


@pytest.mark.parametrize("path", [
    "/annotators?scenes=0", "/annotators?before=soon", "/annotators?colour=red",
    "/annotators/clusters?annotator=SVM", "/annotators/clusters?annotator=a&reference=a&said=x",
])
def test_bad_parameters_of_the_pages_get_a_page_naming_them(client, path):
    answer = client.get(path)
    assert answer.status_code == 422 and 'role="alert"' in answer.text


# --- the page, in Chromium ------------------------------------------------------------------


@pytest.fixture(scope="module")
def tab(store, lab):
    assert CHROMIUM.exists(), "install Debian's chromium: apt-get install -y chromium"
    with served(create_app(store, Settings(consolidator=False))) as url, \
            sync_playwright() as playwright:
        browser = launch(playwright)
        page, blocked = watched(browser)
        page.base = url
        yield page
        assert not blocked, blocked
        browser.close()


def test_the_charts_draw_a_mark_per_hour_with_its_numbers(tab):
    tab.goto(f"{tab.base}/annotators?robot=lab")
    fast = tab.locator('figure.times[data-annotator="Fast"]')
    assert fast.locator("g.hour").count() == 3
    assert fast.locator("circle.p50").count() == fast.locator("circle.p95").count() == 3
    assert fast.locator("polyline.p50").count() == 2  # 8 to 9, then 11: a gap at 10
    assert fast.locator("line.break title").text_content() == (
        "no scene from 2024-03-04 10:00 to 2024-03-04 11:00 UTC")
    assert fast.locator("g.hour title").first.text_content() == (
        "Fast, 2024-03-04 08:00–09:00 UTC: median 15.0 ms, 95th percentile 19.5 ms (2 runs)")
    flaky = tab.locator('figure.times[data-annotator="Flaky"]')
    assert flaky.locator("g.hour").count() == 2  # no run at 11, only an error
    assert tab.locator('figure.rates[data-annotator="Fast"]').count() == 0
    rates = tab.locator('figure.rates[data-annotator="Flaky"]')
    assert rates.locator("g.hour").count() == 3
    assert rates.locator("rect.warned").count() == 2 and rates.locator("rect.failed").count() == 2
    second = rates.locator("g.hour title").nth(1).text_content()
    assert "warned in 1 and failed in 2 of 3 scenes (33%, 67%)" in second
    heights = [float(r.get_attribute("height")) for r in rates.locator("rect.failed").all()]
    assert heights == pytest.approx([40 * 2 / 3, 40], abs=0.1)  # 2 of 3, 1 of 1: of 40 px


def test_confusion_cells_link_to_exactly_their_clusters(tab):
    tab.goto(f"{tab.base}/annotators?robot=lab")
    table = tab.locator(f'section.comparison[data-annotator="SVM"][data-reference="{GROUND_TRUTH}"]'
                        " table.confusion")
    links = table.locator("a[data-count]")
    assert links.count() == 7
    precision = tab.locator('section.comparison[data-annotator="SVM"] tr[data-class="cup"]')
    assert precision.locator(".precision").inner_text() == "0.75"
    for href, count in [(a.get_attribute("href"), a.get_attribute("data-count"))
                        for a in links.all()]:
        tab.goto(tab.base + href)
        assert tab.locator("table.cell-clusters tbody tr").count() == int(count), href
        assert int(count) == int(tab.locator("h1").inner_text().split()[0])
        query = dict(parse_qsl(urlsplit(href).query))
        assert query["robot"] == "lab" and int(query["before"]) > EIGHT


def test_the_marks_and_cells_are_reached_from_the_keyboard(tab):
    tab.goto(f"{tab.base}/annotators?robot=lab")
    seen = []
    for _ in range(80):
        tab.keyboard.press("Tab")
        seen.append(tab.evaluate("[document.activeElement.tagName,"
                                 " document.activeElement.getAttribute('aria-label')"
                                 " || document.activeElement.getAttribute('href')]"))
        if seen[-1][0] == "A" and (seen[-1][1] or "").startswith("/annotators/clusters"):
            break
    marks = [label for tag, label in seen if tag == "g"]
    assert marks[0].startswith("Fast, 2024-03-04 08:00") and len(marks) == 3 + 2 + 3
    tab.keyboard.press("Enter")
    tab.wait_for_load_state("load")
    assert re.match(r"\d+ clusters?", tab.locator("h1").inner_text())
    tab.go_back()  # the page's sections are links before the charts: skip their marks
    tab.locator('nav.sections a[href="#confusion"]').focus()
    tab.keyboard.press("Enter")
    tab.keyboard.press("Tab")
    assert tab.evaluate("document.activeElement.getAttribute('href')").startswith(
        "/annotators/clusters")


def test_screenshot_of_the_annotators_page(tab):
    """The day of the kitchen and the lab: every annotator's times, OCR's warnings, the
    lab's confusion tables (docs/screenshots/annotators.png, in the README)."""
    tab.goto(f"{tab.base}/annotators")
    assert tab.locator("figure.times").count() == 12  # the kitchen's ten and the lab's two
    # the kitchen's classifier and the lab's never classified the same cluster: not compared
    assert tab.locator("section.comparison").count() == 3
    DOCS.mkdir(parents=True, exist_ok=True)
    tab.screenshot(path=str(DOCS / "annotators.png"), full_page=True)


# --- after the page's tests: scenes of 2016 would stretch its time axis over eight years ---


def test_the_ground_truth_of_the_real_robosherlock_store(store, client):
    folder = ROBOSHERLOCK / "mongodump" / "PnP09ObjSymbolicGTFixed"
    store.put_scenes(list(robosherlock.read_dump(folder, robot="pnp09")))
    decaf = comparison(report(client, robot="pnp09"), "DeCafClassifier", GROUND_TRUTH)
    assert (decaf["clusters"], decaf["disagreements"]) == (9, 0)
    assert len(decaf["scores"]) == 7
    assert all(s["precision"] == s["recall"] == 1.0 for s in decaf["scores"])


def test_people_s_corrections_in_force_are_a_reference_too(store, client, lab):
    """A relabel says what a cluster shows; an undone one says nothing."""
    from percept_memory.memory import curation
    from percept_memory.queries.annotators import PEOPLE

    svm_cup, svm_bowl = lab[0].clusters[0], lab[1].clusters[0]
    assert {"cup", "bowl"} == {a.class_name for c in (svm_cup, svm_bowl) for a in c.annotations
                               if isinstance(a, Classification)}
    curation.relabel(store, svm_cup.id, "mug", "ana")
    taken_back = curation.relabel(store, svm_bowl.id, "plate", "ana")
    curation.undo(store, svm_bowl.id, taken_back.id, "ana")
    answer = report(client)
    assert [(c["annotator"], c["reference"]) for c in answer["comparisons"]][:4] == [
        ("SVM", GROUND_TRUTH), ("DeCaf", GROUND_TRUTH), ("DeCaf", PEOPLE), ("SVM", PEOPLE)]
    svm = comparison(answer, "SVM", PEOPLE)
    # the clusters nobody corrected are not compared: every one counted as a disagreement
    assert [(c["said"], c["expected"], c["clusters"]) for c in svm["cells"]] == [
        ("cup", "mug", 1)]
    assert (svm["clusters"], svm["disagreements"]) == (1, 1)


def test_the_cli_s_text_shows_each_comparison_s_cells_and_scores(lab, mongo_uri, db_name):
    """They printed as ', , , ,' (a cell of the table of comparisons)."""
    from click.testing import CliRunner

    from percept_memory.cli import main

    shown = CliRunner().invoke(main, ["query", "annotator-report", "--robot", "lab"],
                               env={"MONGODB_URI": mongo_uri, "PMEM_DB": db_name})
    assert shown.exit_code == 0, shown.output
    text = shown.stdout
    assert ", , ," not in text and "cells:" in text and "scores:" in text
    rows = [line.split() for line in text.splitlines()]
    assert ["cup", "cup", "3"] in rows and ["cup", "0.75", "0.6", "5"] in rows
