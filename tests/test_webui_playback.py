"""Playback (issue 17, part 3): a robot's scenes as a sequence. The steps of the query (checked
against the stored scenes and events, each by an index), GET and POST /api/playback with its
errors, and the playback page in a real headless Chromium: the steps, the time slider, Play,
"next failure" and "next event" go to the right scene, and the belief follows the time.
"""

from __future__ import annotations

import re

import pytest
from bson import ObjectId
from playwright.sync_api import Page, expect

from percept_memory.demo import kitchen_week
from percept_memory.memory.errors import NotFound
from percept_memory.memory.types import LogLine, Scene
from percept_memory.queries.engine import QueryEngine
from percept_memory.webui import render

from . import test_webui
from .conftest import ingest_consolidated
from .test_webui import shot

# test_webui's browser, page, server and client, here on this module's store (filled below)
browser, page, url, client = test_webui.browser, test_webui.page, test_webui.url, test_webui.client

ROBOT, MAP = kitchen_week.ROBOT, kitchen_week.MAP
FAILING = (7, 19)  # scenes of the day where an annotator fails


@pytest.fixture(scope="module")
def week():
    """One kitchen day, where the OCR annotator crashes in two scenes."""
    day = kitchen_week.generate(days=1)
    for k in FAILING:
        day.scenes[k].log.append(LogLine(source="OCRAnnotator", level="error",
                                         message="segmentation fault"))
    return day


@pytest.fixture(scope="module")
def lab(week) -> list[Scene]:
    """Two scenes the robot saw in another map, the day before the kitchen's."""
    start = min(s.timestamp for s in week.scenes) - 86_400 * 10**9
    return [Scene(timestamp=start + i * 60 * 10**9, robot=ROBOT, map="lab") for i in range(2)]


@pytest.fixture(scope="module")
def filled(store, week, lab):
    ingest_consolidated(store, [*lab, *week.scenes])
    return store


@pytest.fixture(scope="module")
def times(filled, week) -> list[int]:
    return sorted(s.timestamp for s in week.scenes)


def failure_times(week) -> list[int]:
    return sorted(week.scenes[k].timestamp for k in FAILING)


def event_times(store, object_id) -> list[int]:
    return sorted(e["time"] for e in store.db.events.find({"object_id": object_id}))


def followed(store, week):
    """An object with several events, and its first event's time."""
    counts = {}
    for e in store.db.events.find({}, {"object_id": 1}):
        counts[e["object_id"]] = counts.get(e["object_id"], 0) + 1
    object_id = max(counts, key=lambda o: (counts[o], str(o)))
    return object_id, event_times(store, object_id)


# --- the query ---------------------------------------------------------------------------------

def test_each_step_goes_to_the_scene_it_names(filled, times):
    engine = QueryEngine(filled)
    k = len(times) // 2
    frame = engine.playback(robot=ROBOT, map=MAP, t=times[k])
    assert (frame.time, frame.first, frame.last) == (times[k], times[0], times[-1])
    assert (frame.previous, frame.next) == (times[k - 1], times[k + 1])
    between = (times[k] + times[k + 1]) // 2
    assert engine.playback(robot=ROBOT, t=between).time == times[k]
    assert engine.playback(robot=ROBOT, t=between, step="next").time == times[k + 1]
    # a step is taken from the scene shown at t (README): the frame's own previous and next
    assert engine.playback(robot=ROBOT, t=between, step="previous").time == times[k - 1]
    assert engine.playback(robot=ROBOT, t=times[k], step="previous").time == times[k - 1]
    assert engine.playback(robot=ROBOT, map=MAP, t=between, step="first").time == times[0]
    assert engine.playback(robot=ROBOT, step="last").time == times[-1]
    assert engine.playback(robot=ROBOT, map=MAP, t=0).time == times[0]  # before the first
    last = engine.playback(robot=ROBOT)
    assert last.time == times[-1] and last.next is None and last.previous == times[-2]


def test_a_map_narrows_the_sequence_to_its_scenes(filled, times, lab):
    engine = QueryEngine(filled)
    everywhere = engine.playback(robot=ROBOT, t=times[0])
    assert (everywhere.first, everywhere.previous) == (lab[0].timestamp, lab[-1].timestamp)
    kitchen = engine.playback(robot=ROBOT, map=MAP, t=times[0])
    assert (kitchen.first, kitchen.previous) == (times[0], None)
    assert engine.playback(robot=ROBOT, map="lab", t=times[5]).time == lab[-1].timestamp
    assert engine.playback(robot=ROBOT, t=0).time == lab[0].timestamp
    with pytest.raises(NotFound):
        engine.playback(robot=ROBOT, map="nowhere")


def test_next_failure_and_next_event(filled, week, times):
    engine = QueryEngine(filled)
    first, second = failure_times(week)
    frame = engine.playback(robot=ROBOT, t=times[0], step="failure")
    assert frame.time == first and frame.failed == ["OCRAnnotator"]
    assert engine.playback(robot=ROBOT, t=first, step="failure").time == second
    # and back (a failure was reached forward only), from the scene shown at a moment
    assert engine.playback(robot=ROBOT, t=second, step="previous_failure").time == first
    assert engine.playback(robot=ROBOT, t=second + 1, step="previous_failure").time == first
    assert engine.playback(robot=ROBOT, t=first).failed == ["OCRAnnotator"]
    assert engine.playback(robot=ROBOT, t=first, step="next").failed == []
    object_id, events = followed(filled, week)
    for before, after in zip(events, events[1:], strict=False):
        assert engine.playback(robot=ROBOT, t=before, step="event",
                               object=object_id).time == after


def test_every_step_is_an_index_seek(filled):
    for step, extra in (("at", {}), ("next", {}), ("failure", {}), ("first", {}),
                        ("previous_failure", {}),
                        ("event", {"object": filled.db.events.find_one()["object_id"]})):
        plans: list = []
        t = None if step == "previous_failure" else 0  # (now: there are failures before it)
        QueryEngine(filled, explain=plans).playback(robot=ROBOT, t=t, step=step, **extra)
        assert plans
        for plan in plans:
            assert "COLLSCAN" not in plan["stages"] and plan["indexes"], (step, plan)
        if step == "failure":
            assert plans[0]["indexes"] == ["robot_failed_time"], plans[0]
        if step == "previous_failure":  # (after the seek of the scene shown)
            assert plans[1]["indexes"] == ["robot_failed_time"], plans


# --- the API -------------------------------------------------------------------------------

def test_the_api_answers_a_step_by_get_and_post(client, times):
    by_get = client.get("/api/playback", params={"robot": ROBOT, "t": times[3], "step": "next"})
    by_post = client.post("/api/playback", json={"robot": ROBOT, "t": times[3], "step": "next"})
    assert by_get.status_code == by_post.status_code == 200, by_get.text
    assert by_get.json() == by_post.json()
    assert by_get.json()["time"] == times[4] and by_get.json()["previous"] == times[3]


@pytest.mark.parametrize("params, status", [
    ({}, 422),
    ({"robot": ROBOT, "step": "sideways"}, 422),
    ({"robot": ROBOT, "t": "yesterday"}, 422),
    ({"robot": ROBOT, "t": "-1"}, 422),
    ({"robot": ROBOT, "step": "event"}, 422),
    ({"robot": ROBOT, "step": "next", "object": str(ObjectId())}, 422),
    ({"robot": ROBOT, "step": "event", "object": "zz"}, 422),
    ({"robot": ROBOT, "colour": "red"}, 422),
    ({"robot": "nobody"}, 404),
    ({"robot": ROBOT, "map": "nowhere"}, 404),
    ({"robot": ROBOT, "map": ""}, 422),
    ({"robot": ROBOT, "step": "next", "t": str(2**63 - 1)}, 404),
    ({"robot": ROBOT, "step": "event", "object": str(ObjectId())}, 404),
])
def test_bad_playback_requests_get_the_json_error(client, params, status):
    answer = client.get("/api/playback", params=params)
    assert answer.status_code == status, answer.text
    error = answer.json()["error"]
    assert error["status"] == status and error["message"]


def test_no_failure_after_the_last_is_a_404_naming_it(client, week):
    last = failure_times(week)[-1]
    answer = client.get("/api/playback", params={"robot": ROBOT, "t": last, "step": "failure"})
    assert answer.status_code == 404
    assert "where an annotator failed" in answer.json()["error"]["message"]


@pytest.mark.parametrize("query", ["robot=nobody", "t=yesterday", "at=soon", "object=zz",
                                   "t=5&at=5", "map=nowhere", "map=" + "x" * 300])
def test_bad_parameters_of_the_page_get_a_page_naming_the_problem(client, query):
    answer = client.get(f"/playback?{query}")
    assert answer.status_code in (404, 422) and 'role="alert"' in answer.text


def test_no_parameter_value_gives_a_server_error(client):
    for name in ("robot", "map", "t", "at", "object"):
        for value in test_webui.NASTY:
            answer = client.get("/playback", params={name: value})
            assert answer.status_code < 500, (name, value, answer.text[-500:])


def test_the_belief_is_drawn_as_on_the_map_page(client, times):
    """Playback draws its map's belief as the map page does (belief_map.drawn_belief): the
    same labels placed apart, crowds and hidden objects fading with their age."""
    t = times[-1]
    figures = [re.search(r'<figure class="map">.*?</figure>', client.get(path).text, re.S)[0]
               for path in (f"/playback?robot={ROBOT}&t={t}", f"/map?map={MAP}&t={t}")]
    assert figures[0] == figures[1]
    assert 'lengthAdjust="spacingAndGlyphs"' in figures[0] and ' opacity="0.' in figures[0]


# --- in the browser --------------------------------------------------------------------------

def shown_time(page: Page) -> int:
    return int(page.locator("#frame").get_attribute("data-time"))


def test_steps_and_the_slider_change_the_scene_and_the_belief(page, url, times):
    k = 5
    page.goto(f"{url}/playback?robot={ROBOT}&t={times[k]}")
    assert shown_time(page) == times[k]
    belief = page.locator("figure.map svg").inner_html()
    page.get_by_role("link", name="next", exact=True).click()
    expect(page.locator("#frame")).to_have_attribute("data-time", str(times[k + 1]))
    expect(page.locator("#shown-scene")).to_contain_text(render.time_of(times[k + 1]))
    expect(page).to_have_url(f"{url}/playback?robot={ROBOT}&t={times[k + 1]}")
    assert page.locator("figure.map svg").inner_html() != belief  # the map's moment moved on
    page.get_by_role("link", name="previous", exact=True).click()
    expect(page.locator("#frame")).to_have_attribute("data-time", str(times[k]))
    page.locator("input[name=at]").fill(str(-(-times[k + 3] // 10**9)))
    expect(page.locator("#frame")).to_have_attribute("data-time", str(times[k + 3]))
    page.get_by_role("link", name="last", exact=True).click()
    expect(page.locator("#frame")).to_have_attribute("data-time", str(times[-1]))
    expect(page.locator("nav.steps a[rel=next]")).to_have_count(0)


def test_the_arrow_keys_step_and_a_scene_page_leads_here(page, url, week, times):
    scene = next(s for s in week.scenes if s.timestamp == times[4])
    page.goto(f"{url}/scenes/{scene.id}")
    page.get_by_role("link", name="play from here").click()
    expect(page.locator("#frame")).to_have_attribute("data-time", str(times[4]))
    page.keyboard.press("ArrowRight")
    expect(page.locator("#frame")).to_have_attribute("data-time", str(times[5]))
    page.keyboard.press("ArrowLeft")
    page.keyboard.press("ArrowLeft")
    expect(page.locator("#frame")).to_have_attribute("data-time", str(times[3]))


def test_play_advances_until_paused(page, url, times):
    page.goto(f"{url}/playback?robot={ROBOT}&t={times[0]}")
    page.get_by_role("button", name="Play").click()
    expect(page.locator("#frame")).to_have_attribute("data-time", str(times[1]), timeout=5000)
    expect(page.locator("#frame")).to_have_attribute("data-time", str(times[2]), timeout=5000)
    page.get_by_role("button", name="Pause").click()
    stopped = shown_time(page)
    page.wait_for_timeout(2500)
    assert shown_time(page) == stopped <= times[3]


def test_next_failure_and_next_event_jump_to_their_scenes(page, url, store, week, times):
    first, second = failure_times(week)
    page.goto(f"{url}/playback?robot={ROBOT}&t={times[0]}")
    page.get_by_role("link", name="next failure").click()
    expect(page.locator("#frame")).to_have_attribute("data-time", str(first))
    expect(page.locator("#frame .failed")).to_have_text("OCRAnnotator")
    page.get_by_role("link", name="next failure").click()
    expect(page.locator("#frame")).to_have_attribute("data-time", str(second))
    shot(page, "15-playback")

    object_id, events = followed(store, week)
    page.goto(f"{url}/playback?robot={ROBOT}&t={events[0]}")
    page.locator("select[name=object]").select_option(str(object_id))
    page.get_by_role("button", name="Follow").click()
    name = store.db.objects.find_one({"_id": object_id})["name"]
    for after in events[1:4]:
        page.get_by_role("link", name=f"next event of {name}").click()
        expect(page.locator("#frame")).to_have_attribute("data-time", str(after))
    expect(page).to_have_url(f"{url}/playback?robot={ROBOT}&t={events[3]}&object={object_id}")


def test_a_chosen_map_stays_chosen(page, url, times):
    page.goto(f"{url}/playback?robot={ROBOT}&t={times[0]}")
    expect(page.get_by_role("link", name="previous", exact=True)).to_have_count(1)  # the lab
    page.locator("select[name=map]").select_option(MAP)
    expect(page).to_have_url(f"{url}/playback?robot={ROBOT}&map={MAP}&at={times[0] // 10**9 + 1}")
    expect(page.locator("#frame")).to_have_attribute("data-time", str(times[0]))
    expect(page.locator("nav.steps .off", has_text=re.compile("^previous$"))).to_have_count(1)
    page.get_by_role("link", name="next", exact=True).click()
    expect(page).to_have_url(f"{url}/playback?robot={ROBOT}&t={times[1]}&map={MAP}")


def test_the_timeline_marks_failures_and_events_and_leads_to_them(page, url, store, week,
                                                                  times):
    first, second = failure_times(week)
    object_id, events = followed(store, week)
    page.goto(f"{url}/playback?robot={ROBOT}&map={MAP}&t={times[0]}&object={object_id}")
    failures, marked = page.locator("a.mark.failure"), page.locator("a.mark.event")
    expect(failures).to_have_count(2)
    expect(marked).to_have_count(len(events))
    failures.nth(1).locator("rect").click()
    expect(page.locator("#frame")).to_have_attribute("data-time", str(second))
    marked.last.locator("rect").click()  # drawn last, so on top of any it overlaps
    expect(page.locator("#frame")).to_have_attribute("data-time", str(events[-1]))


def test_without_javascript_the_steps_are_links(browser, url, times):
    context = browser.new_context(java_script_enabled=False)
    tab = context.new_page()
    tab.goto(f"{url}/playback?robot={ROBOT}&t={times[2]}")
    expect(tab.get_by_role("button", name="Play")).to_have_count(0)
    tab.get_by_role("link", name="next", exact=True).click()
    expect(tab.locator("#frame")).to_have_attribute("data-time", str(times[3]))
    tab.get_by_role("button", name="Show").click()  # the slider as it stands: the same scene
    expect(tab.locator("#frame")).to_have_attribute("data-time", str(times[3]))
    context.close()
