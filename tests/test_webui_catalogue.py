"""The catalogue page in a real headless Chromium, on three days of the kitchen week."""

from __future__ import annotations

import pytest
from playwright.sync_api import sync_playwright

from percept_memory.demo import kitchen_week
from percept_memory.memory.settings import Settings
from percept_memory.queries import catalogue
from percept_memory.webui.app import create_app

from .conftest import ingest_consolidated, served
from .test_webui import ALL_LOADED, SCREENSHOTS
from .test_webui_curation import launch, watched


@pytest.fixture(scope="module")
def url(store):
    ingest_consolidated(store, kitchen_week.generate(days=4).scenes)
    with served(create_app(store, Settings())) as url:
        yield url


def test_the_catalogue_page_shows_every_entry_with_its_views(url, store):
    entries = catalogue.entries(store)
    with sync_playwright() as playwright:
        browser = launch(playwright)
        tab, blocked = watched(browser)
        tab.goto(f"{url}/")
        tab.get_by_role("link", name="Catalogue").click()
        tab.wait_for_load_state("load")
        rows = tab.locator("table.catalogue tbody tr")
        assert rows.count() == len(entries)
        first = entries[0]
        row = tab.locator(f"#entry-{first['entry']}")
        assert row.locator("img.crop").count() == len(first["views"])
        assert tab.evaluate(ALL_LOADED), "a crop did not decode"
        assert first["names"][0] in row.inner_text()
        for entry in entries:  # each entry's models and links, drawn
            drawing = tab.locator(f"#entry-{entry['entry']} svg.similarity")
            assert drawing.locator("circle").count() == entry["models"]
            assert drawing.locator("line").count() == len(entry["graph"]["links"])
        changes = catalogue.history(store, limit=30)
        assert changes, "four days of the kitchen merge or split some entries"
        items = tab.locator("ol.changes li")
        assert items.count() == len(changes)
        for change, item in zip(changes, items.all(), strict=True):
            assert item.get_attribute("class") == change["kind"]
            assert item.locator("a[href^='#entry-']").count() == len(change["current"])
            pictures = len(change["before"]) + len(change["after"]) + 1  # and the observation
            assert item.locator("img.crop").count() == pictures
        SCREENSHOTS.mkdir(parents=True, exist_ok=True)
        tab.screenshot(path=str(SCREENSHOTS / "catalogue.png"), full_page=False)
        current = tab.locator("ol.changes a[href^='#entry-']").first
        current.focus()
        tab.keyboard.press("Enter")
        assert tab.evaluate("document.querySelector(location.hash) !== null")
        row.locator(f"a[href='/objects/{first['now']['object_id']}']").click()
        tab.wait_for_load_state("load")
        assert tab.url.endswith(f"/objects/{first['now']['object_id']}")
        tab.goto(f"{url}/catalogue?map=nowhere")
        assert "Nothing learnt yet" in tab.locator("table.catalogue").inner_text()
        assert "No entry has merged or split" in tab.locator("ol.changes").inner_text()
        browser.close()
    assert not blocked, f"the page broke its own Content-Security-Policy: {blocked}"
