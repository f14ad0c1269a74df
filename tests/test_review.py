"""The review queue (queries/review.py, webui/review.py) on a day of the kitchen week: ranked
by doubt, an annotator's disagreement and identity's close calls among the first, corrected
clusters leave it and are counted; in Chromium, 20 labels corrected one after another by
keyboard."""

from __future__ import annotations

import pytest
from fastapi.testclient import TestClient
from playwright.sync_api import expect

from percept_memory.demo import kitchen_week
from percept_memory.memory import curation
from percept_memory.memory.naming import naming_labels
from percept_memory.memory.settings import Settings
from percept_memory.memory.types import Classification, Rejection, Relabel
from percept_memory.queries.review import review_queue
from percept_memory.webui.app import create_app

from .conftest import LOCAL, ingest_consolidated
from .test_webui import SCREENSHOTS
from .test_webui_curation import in_chromium


@pytest.fixture(scope="module")
def memory(store):
    ingest_consolidated(store, kitchen_week.generate(days=1).scenes)
    return store


@pytest.fixture(scope="module")
def disputed(memory):
    """A cluster a second classifier, quite sure of itself, calls something else."""
    doc = memory.clusters.find_one({"annotations._type": "pm.annotation.Classification"},
                                   sort=[("search.time", -1)])
    memory.add_annotation(doc["_id"], Classification(source="RivalClassifier",
                                                     class_name="flower pot", confidence=0.95))
    return memory.get_cluster(doc["_id"])


def test_the_queue_is_ranked_by_doubt_and_explains_it(memory, disputed):
    queue = review_queue(memory, shown=500)
    scores = [d.score for d in queue.doubts]
    assert scores == sorted(scores, reverse=True) and queue.clusters > len(queue.doubts) / 2
    (mine,) = [d for d in queue.doubts if d.cluster_id == disputed.id]
    names = naming_labels(disputed.annotations)
    assert "flower pot" in dict(mine.names)
    assert mine.disagreement == round(1 - max(names.values()) / sum(names.values()), 3) > 0.3
    close = [d for d in queue.doubts if d.decision]
    assert close and all(0 <= d.closeness <= 1 for d in close)
    for doubt in close:  # the alternative is another option than the decision taken
        alternative = doubt.decision["alternative"]
        assert (alternative["explanation"], alternative.get("object_id")) != (
            doubt.decision["explanation"], doubt.object_id)


def test_a_corrected_cluster_leaves_the_queue_and_counts_as_fixed(memory, disputed):
    before = review_queue(memory, shown=500)
    first = before.doubts[0]
    curation.relabel(memory, first.cluster_id, "cup", author="ana")
    after = review_queue(memory, shown=500)
    assert after.fixed == before.fixed + 1
    assert first.cluster_id not in {d.cluster_id for d in after.doubts}


def test_the_json_twin_answers_the_same_and_refuses_bad_windows(memory, disputed):
    client = TestClient(create_app(memory, Settings(consolidator=False)), base_url=LOCAL)
    answer = client.get("/api/review", params={"shown": 10})
    assert answer.status_code == 200
    body = answer.json()
    queue = review_queue(memory, shown=10)
    assert [d["cluster_id"] for d in body["doubts"]] == [str(d.cluster_id) for d in queue.doubts]
    assert body["fixed"] == queue.fixed and body["doubts"][0]["score"] == queue.doubts[0].score
    for params in ({"scenes": 0}, {"shown": 501}, {"scenes": "many"}):
        error = client.get("/api/review", params=params)
        assert error.status_code == 422 and error.json()["error"]["problems"]
    assert client.get("/review", params={"scenes": "0"}).status_code == 422


def test_twenty_labels_are_corrected_by_keyboard_from_the_queue(memory, disputed):
    queue = review_queue(memory, shown=20)
    assert len(queue.doubts) == 20
    with in_chromium(memory) as (tab, url):
        tab.goto(f"{url}/review?shown=20")
        tab.locator("#author").fill("ana")
        SCREENSHOTS.mkdir(parents=True, exist_ok=True)
        tab.screenshot(path=str(SCREENSHOTS / "review.png"), full_page=False)
        rows = tab.locator("table.review tbody tr")
        first = rows.first.locator("input[name=label]")
        first.focus()
        for number in range(20):
            tab.keyboard.type(f"thing {number}")
            tab.keyboard.press("Enter")
            expect(rows.nth(number).locator("form.relabel [role=status]")).to_have_text("Saved.")
            if number < 19:
                expect(rows.nth(number + 1).locator("input[name=label]")).to_be_focused()
        expect(tab.locator("strong.fixed")).to_have_text(str(queue.fixed + 20))  # (as it went)
        tab.reload()
        expect(tab.locator("strong.fixed")).to_have_text(str(queue.fixed + 20))
    labels = {memory.get_cluster(d.cluster_id).annotations[-1].class_name for d in queue.doubts}
    assert labels == {f"thing {n}" for n in range(20)}
    assert all(isinstance(memory.get_cluster(d.cluster_id).annotations[-1], Relabel)
               for d in queue.doubts)


def test_a_row_takes_no_second_correction_while_its_first_is_saved(memory, disputed):
    """Enter on a relabel then Tab, Tab, Tab, Enter before the answer came (the focus still in
    the row) rejected the cluster too, 69 ms later."""
    queue = review_queue(memory, shown=30)
    doubt = queue.doubts[-1]
    with in_chromium(memory) as (tab, url):
        tab.goto(f"{url}/review?shown=30")
        tab.locator("#author").fill("ana")
        row = tab.locator("table.review tbody tr").last
        held = []  # the relabel's request, answered once the keys are pressed
        tab.route("**/relabel", lambda route: held.append(route))
        row.locator("input[name=label]").fill("mug")
        row.locator("input[name=label]").press("Enter")
        expect(row.locator("form.relabel [role=status]")).to_have_text("Saving…")
        for key in ("Tab", "Tab", "Tab", "Enter"):
            tab.keyboard.press(key)
        tab.wait_for_timeout(200)
        (request,) = held
        request.continue_()
        expect(row.locator("form.relabel [role=status]")).to_have_text("Saved.")
        tab.wait_for_timeout(200)
    said = memory.get_cluster(doubt.cluster_id).annotations
    assert [type(a).__name__ for a in said if a.source == "human"] == ["Relabel"]


def test_a_detection_is_rejected_from_the_queue_by_keyboard(memory, disputed):
    queue = review_queue(memory, shown=3)
    with in_chromium(memory) as (tab, url):
        tab.goto(f"{url}/review?shown=3")
        tab.locator("#author").fill("ana")
        rows = tab.locator("table.review tbody tr")
        rows.first.locator("form.reject input[name=reason]").focus()
        tab.keyboard.type("a reflection")
        tab.keyboard.press("Tab")  # to "This detection is wrong"
        tab.keyboard.press("Enter")
        expect(rows.first.locator("form.reject [role=status]")).to_have_text("Saved.")
        expect(rows.nth(1).locator("input[name=label]")).to_be_focused()
    said = memory.get_cluster(queue.doubts[0].cluster_id).annotations[-1]
    assert isinstance(said, Rejection) and said.reason == "a reflection"
