"""The 3D views (issue 17, part 2) in a real headless Chromium: what the WebGL canvas shows of a
real RGB-D scene (RoboSherlock's kitchen frame), of a real cloud (low_noise) and of the kitchen
week's map, that dragging turns it, and the binary points route with its limits and errors.

WebGL runs on Chromium's software rasteriser (SwiftShader): the fixture's flags suffice.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from bson import ObjectId
from playwright.sync_api import Page, expect

from percept_memory.demo import kitchen_week
from percept_memory.ingest.rgbd import read_samples
from percept_memory.memory.types import PointCluster
from percept_memory.queries import scene3d

from . import test_webui
from .conftest import ROBOSHERLOCK, ingest_consolidated
from .test_webui import shot

# test_webui's fixtures, here on this module's store (filled below)
browser, page, url, client, week, sample = (test_webui.browser, test_webui.page, test_webui.url,
                                            test_webui.client, test_webui.week, test_webui.sample)

DRAWN = "canvas.view3d[data-drawn]"


@pytest.fixture(scope="module")
def table():
    """The real low_noise table frames: PCD clouds with colours and labelled segments."""
    return list(read_samples(ROBOSHERLOCK / "samples" / "low_noise", robot="pr2-table"))


@pytest.fixture(scope="module")
def filled(store, week, sample, table):
    ingest_consolidated(store, week.scenes)
    store.put_scenes([sample, *table])
    store.outbox.delete_many({"_id": {"$in": [sample.id, *(s.id for s in table)]}})
    return store


def canvas_pixels(page: Page) -> np.ndarray:
    """What the user sees of the 3D view: the canvas as shown on screen, BGR."""
    png = page.locator("canvas.view3d").screenshot()
    return cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)


def colours(image: np.ndarray) -> int:
    return len(np.unique(image.reshape(-1, 3), axis=0))


def test_a_scene_in_3d_shows_its_points_boxes_and_camera(page, url, sample):
    """From the scene page, the 3D link: the canvas shows the sampled points in their
    colours, red cluster boxes and the blue frustum; the image and its boxes stay."""
    page.goto(f"{url}/scenes/{sample.id}")
    page.get_by_role("link", name="3D", exact=True).click()
    expect(page).to_have_url(f"{url}/scenes/{sample.id}?view=3d")
    expect(page.locator("canvas.view3d[data-points='200000']")).to_have_count(1)
    seen = canvas_pixels(page)
    assert colours(seen) > 1000  # the kitchen counter's colours, not a blank canvas
    background = np.all(seen == seen[0, 0], axis=2).mean()
    assert background < 0.9
    b, g, r = (seen[..., i].astype(int) for i in range(3))
    assert ((r > 200) & (g < 90) & (b < 90)).sum() > 50, "no red cluster box"
    expect(page.locator("figure.viewer img")).to_have_count(2)  # colour and depth stay
    expect(page.locator("#image-color form.layers")).to_be_visible()  # viewer.js runs too
    shot(page, "13-scene-3d")


def test_dragging_turns_the_view(page, url, table):
    page.goto(f"{url}/scenes/{table[0].id}?view=3d")
    expect(page.locator(f"canvas.view3d[data-points='{len(table[0].clouds['cloud'].points)}']")
           ).to_have_count(1)
    before = canvas_pixels(page)
    drawn = int(page.locator(DRAWN).get_attribute("data-drawn"))
    box = page.locator("canvas.view3d").bounding_box()
    x, y = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
    page.mouse.move(x, y)
    page.mouse.down()
    page.mouse.move(x + 160, y + 40, steps=8)
    page.mouse.up()
    assert int(page.locator(DRAWN).get_attribute("data-drawn")) > drawn
    after = canvas_pixels(page)
    assert np.abs(after.astype(int) - before.astype(int)).mean() > 2, "the view did not turn"
    assert colours(after) > 100


def test_the_map_in_3d_follows_the_chosen_time(page, url, week):
    """The map page's 3D view: regions and the objects believed at the moment; the time
    links keep the 3D view and the table stays."""
    k = len(week.scenes) // 2
    at = week.scenes[k].timestamp // 10**9 + 1
    page.goto(f"{url}/map?map={kitchen_week.MAP}&at={at}&view=3d")
    expect(page.locator(DRAWN)).to_have_count(1)
    seen = canvas_pixels(page)
    assert colours(seen) > 20
    b, g, r = (seen[..., i].astype(int) for i in range(3))
    assert ((b > 150) & (r < 60)).sum() > 20, "no blue object dot"
    rows = page.locator("table.believed tbody tr.present").count()
    assert rows > 0
    drawn = page.evaluate("JSON.parse(document.getElementById('view3d-data').textContent)")
    assert sum(o["state"] == "present" for o in drawn["objects"]) == rows
    assert {b["label"] for b in drawn["boxes"]} == set(kitchen_week.REGIONS)
    shot(page, "14-map-3d")
    page.get_by_role("link", name="scene before").click()
    expect(page).to_have_url(
        f"{url}/map?map={kitchen_week.MAP}&t={week.scenes[k].timestamp}&view=3d")
    expect(page.locator(DRAWN)).to_have_count(1)


# --- the shapes -------------------------------------------------------------------------------

def test_the_frustum_is_the_camera_and_its_image_corners(sample):
    apex, *corners = np.array(scene3d.shapes(sample).frustum)
    assert np.allclose(apex, sample.camera_pose.translation)
    to_camera = np.linalg.inv(sample.camera_pose.matrix())
    x, y, z = (np.array(corners) @ to_camera[:3, :3].T + to_camera[:3, 3]).T
    (fx, fy), (cx, cy) = sample.camera.focal, sample.camera.principal_point
    width, height = sample.camera.width, sample.camera.height
    assert np.allclose(fx * x / z + cx, [0, width, width, 0])
    assert np.allclose(fy * y / z + cy, [0, 0, height, height])


def test_the_depth_image_gives_the_points_the_importer_found(sample):
    """Every cluster's points (the importer's, from the same depth) are among the scene's."""
    from scipy.spatial import cKDTree

    whole = cKDTree(scene3d.points(sample, max_points=10**7)[0])
    for cluster in sample.clusters:
        own = cluster.hypothesis_of(PointCluster).points.xyz()
        assert whole.query(own)[0].max() < 1e-5


# --- plain HTTP -------------------------------------------------------------------------------

def test_the_points_route_sends_at_most_what_is_asked(client, sample, table):
    shapes = scene3d.shapes(sample)
    for asked, expected in ((1000, 1000), (None, scene3d.MAX_POINTS)):
        answer = client.get(f"/api/scenes/{sample.id}/cloud",
                            params={} if asked is None else {"max_points": asked})
        assert answer.status_code == 200
        assert answer.headers["content-type"] == "application/octet-stream"
        assert int(answer.headers["x-points"]) == expected == len(answer.content) // 15
        xyz = np.frombuffer(answer.content, "<f4", expected * 3).reshape(-1, 3)
        rgb = np.frombuffer(answer.content, np.uint8, offset=expected * 12).reshape(-1, 3)
        assert np.isfinite(xyz).all() and len(np.unique(rgb, axis=0)) > 100
        low, high = (np.array([b.low for b in shapes.boxes]).min(axis=0),
                     np.array([b.high for b in shapes.boxes]).max(axis=0))
        assert (xyz.min(axis=0) <= low + 1e-3).all() and (xyz.max(axis=0) >= high - 1e-3).all()
    assert shapes.points > scene3d.MAX_POINTS  # the depth image has more than are sent
    whole = client.get(f"/api/scenes/{table[0].id}/cloud")
    assert int(whole.headers["x-points"]) == len(table[0].clouds["cloud"].points)


def test_the_same_points_every_time(client, sample):
    first, second = (client.get(f"/api/scenes/{sample.id}/cloud", params={"max_points": 500})
                     for _ in range(2))
    assert first.content == second.content


def test_a_scene_without_points_has_boxes_and_a_camera(client, week):
    scene = week.scenes[0]
    answer = client.get(f"/api/scenes/{scene.id}/cloud")
    assert answer.status_code == 200 and answer.content == b""
    shapes = scene3d.shapes(scene)
    assert len(shapes.boxes) == len(scene.clusters) and shapes.frustum is not None
    body = client.get(f"/scenes/{scene.id}?view=3d").text
    assert '"cloud": null' in body and 'id="view3d-data"' in body


@pytest.mark.parametrize("path, params, status", [
    ("/api/scenes/nonsense/cloud", {}, 422),
    ("/api/scenes/<script>/cloud", {}, 422),
    (f"/api/scenes/{ObjectId()}/cloud", {}, 404),
    ("/api/scenes/{sample}/cloud", {"max_points": 0}, 422),
    ("/api/scenes/{sample}/cloud", {"max_points": 200_001}, 422),
    ("/api/scenes/{sample}/cloud", {"max_points": "many"}, 422),
])
def test_bad_points_requests_get_the_json_error(client, sample, path, params, status):
    answer = client.get(path.format(sample=sample.id), params=params)
    assert answer.status_code == status, answer.text
    error = answer.json()["error"]
    assert error["status"] == status and error["message"]


def test_only_the_3d_views_run_their_script_and_fetch(client, sample):
    """In 2D the map runs no script and the scene page with images only its viewer, which
    fetches nothing; in 3D both run view3d.js, which fetches the points."""
    for path in (f"/scenes/{sample.id}?", f"/map?map={kitchen_week.MAP}&"):
        flat = client.get(path)
        policy = flat.headers["content-security-policy"]
        assert "connect-src" not in policy and "view3d.js" not in flat.text
        assert ("script-src 'self'" in policy) == path.startswith("/scenes")  # viewer.js
        solid = client.get(path + "view=3d")
        assert "script-src 'self'" in solid.headers["content-security-policy"]
        assert "connect-src 'self'" in solid.headers["content-security-policy"]
        assert '<script type="module" src="/static/ui/view3d.js">' in solid.text
        refused = client.get(path + "view=4d")
        assert refused.status_code == 422 and 'role="alert"' in refused.text


def test_three_js_is_served_from_this_site(client):
    for name in ("three.module.js", "three.core.js", "OrbitControls.js"):
        script = client.get(f"/static/ui/three/{name}")
        assert script.status_code == 200 and "javascript" in script.headers["content-type"]
    controls = client.get("/static/ui/three/OrbitControls.js").text
    assert "from './three.module.js'" in controls and "from 'three'" not in controls
