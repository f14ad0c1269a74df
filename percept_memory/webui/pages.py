"""The HTML pages (issue 7, after the thesis' web page, Blodow 6.6 / fig. 6.11): a scene with
its image, cluster boxes, log, relations and annotations, and a cluster; `mount_pages` adds
them and the pages of the other modules (scene log, object history, search, map, annotators,
enrichment, live, playback). Server-rendered, no JavaScript (html.py: what pages share) but
for the scene's images, whose small script switches what is drawn on them and zooms
(viewer.py), the 3D view a scene or map page adds with `view=3d` (scene3d.py), the playback's
steps without reload and the live page's updates.
"""

from __future__ import annotations

from dataclasses import dataclass

from bson import ObjectId
from fastapi import APIRouter, FastAPI, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import FileResponse, HTMLResponse, Response
from fastapi.staticfiles import StaticFiles

from percept_memory.memory.errors import NotFound
from percept_memory.memory.schema import EVENTS, OBJECTS
from percept_memory.memory.settings import Settings
from percept_memory.memory.store import MemoryStore
from percept_memory.memory.types import Image, ImageROI, Scene
from percept_memory.queries.engine import QueryEngine

from . import (
    annotators,
    belief_map,
    curation,
    enrichment,
    history,
    live,
    pipeline,
    playback,
    render,
    scene3d,
    scene_log,
    search,
    viewer,
)
from .html import CSP, HERE, LIST_FIELDS, SCRIPT_CSP, VIEWER_CSP, PageError, page, parse_id
from .images import display_png

THUMB_SIDE = 160
PLAN_WIDTH, PLAN_HEIGHT = 640, 400
CACHED = {"Cache-Control": "max-age=3600"}  # nosniff and the rest: guard.py, on all
# what a page's <img> of a scene or cluster with no pixels shows (a list row does not know
# before asking: a broken image, a 404 in the console, said nothing)
NO_IMAGE = Response(
    '<svg xmlns="http://www.w3.org/2000/svg" width="64" height="48" viewBox="0 0 64 48">'
    '<rect width="64" height="48" fill="#eee"/><text x="32" y="28" font-size="9" '
    'font-family="sans-serif" text-anchor="middle" fill="#666">no image</text></svg>',
    media_type="image/svg+xml", headers=CACHED)


def mount_pages(app: FastAPI, store: MemoryStore, settings: Settings) -> None:
    """Add the pages, their images, style sheets, scripts and icon to the app."""
    app.mount("/static/ui", StaticFiles(directory=HERE / "static"), name="ui-static")

    @app.get("/favicon.ico", include_in_schema=False)
    def favicon() -> FileResponse:
        return FileResponse(HERE / "static" / "favicon.ico", headers=CACHED)

    engine = QueryEngine(store, settings)
    for router in (scene_log.routes(store), page_routes(store), history.routes(store),
                   search.routes(store, engine), belief_map.routes(store, engine),
                   annotators.routes(store, engine), enrichment.routes(store),
                   pipeline.routes(store), playback.routes(store, engine),
                   live.routes(store)):
        app.include_router(router)

    @app.exception_handler(PageError)
    async def _page_error(request: Request, error: PageError) -> HTMLResponse:
        return page(request, "error.html", {"error": error}, error.status)


def page_routes(store: MemoryStore) -> APIRouter:
    router = APIRouter(include_in_schema=False, default_response_class=HTMLResponse)
    objects, events = store.db[OBJECTS], store.db[EVENTS]

    async def stored(get, text: str, kind: str):
        """The stored scene or cluster an URL names, or a 404 page."""
        return await run_in_threadpool(_found, get, parse_id(text, kind))

    @router.get("/scenes/{scene_id}")
    async def scene_page(request: Request, scene_id: str, view: str = "") -> HTMLResponse:
        in_3d = scene3d.wanted(view)
        scene = await stored(store.get_scene, scene_id, "scene")

        def load() -> tuple[dict, dict]:
            ids = [c.object_id for c in scene.clusters if c.object_id]
            names = {o["_id"]: o.get("name") for o in objects.find({"_id": {"$in": ids}},
                                                                    {"name": 1})}
            explained = {e["cluster_id"]: e for e in events.find({"scene_id": scene.id})
                         if e.get("cluster_id")}
            return names, explained

        names, explained = await run_in_threadpool(load)
        plan = None if scene.images else await run_in_threadpool(_plan, store, scene)
        solid = await run_in_threadpool(scene3d.scene_view, scene, names) if in_3d else None
        return page(request, "scene.html", {
            "scene": scene, "names": names, "events": explained,
            "overlays": viewer.overlays(scene, names),
            "log": render.log_by_annotator(scene.log), "plan": plan, "view3d": solid,
        }, policy=SCRIPT_CSP if in_3d else VIEWER_CSP if scene.images else CSP)

    @router.get("/clusters/{cluster_id}")
    async def cluster_page(request: Request, cluster_id: str) -> HTMLResponse:
        cluster = await stored(store.get_cluster, cluster_id, "cluster")

        def load() -> tuple[dict | None, dict | None, list[dict], dict]:
            scene = store.scenes.find_one({"_id": cluster.scene_id}, LIST_FIELDS)
            believed = objects.find_one({"_id": cluster.object_id}) if cluster.object_id else None
            # by the events' scene index (cluster_id alone has none: a scan of all events)
            explained = list(events.find({"scene_id": cluster.scene_id,
                                          "cluster_id": cluster.id}))
            considered = [a["object_id"] for e in explained for a in e.get("alternatives", [])
                          if a.get("object_id")]
            names = {o["_id"]: o.get("name") for o in objects.find({"_id": {"$in": considered}},
                                                                    {"name": 1})}
            return scene, believed, explained, names

        scene, believed, explained, names = await run_in_threadpool(load)
        return page(request, "cluster.html", {
            "cluster": cluster, "roi": cluster.hypothesis_of(ImageROI), "scene": scene,
            "object": believed, "events": explained, "names": names,
            "versus_truth": curation.versus_truth(cluster),
        }, policy=SCRIPT_CSP)  # its correction forms' script (curation.py)

    @router.get("/img/scenes/{scene_id}/images/{name:path}")  # (a name may hold a /)
    async def scene_image(scene_id: str, name: str) -> Response:
        scene = await stored(store.get_scene, scene_id, "scene")
        if name not in scene.images:
            raise PageError(404, f"scene {scene_id} has no image {name!r}")
        return await _png(scene.images[name])

    @router.get("/img/scenes/{scene_id}/thumb")
    async def scene_thumbnail(scene_id: str) -> Response:
        """The scene's first image, else its first cluster's crop, shrunk."""
        scene = await stored(store.get_scene, scene_id, "scene")
        crops = (roi.crop for c in scene.clusters if (roi := c.hypothesis_of(ImageROI)))
        image = next(iter(scene.images.values()), None) or next(filter(None, crops), None)
        if image is None:  # (its clusters may be positions alone, or its files left out)
            return NO_IMAGE
        return await _png(image, THUMB_SIDE)

    @router.get("/img/clusters/{cluster_id}/crop")
    async def cluster_crop(cluster_id: str) -> Response:
        cluster = await stored(store.get_cluster, cluster_id, "cluster")
        roi = cluster.hypothesis_of(ImageROI)
        if roi is None or roi.crop is None:
            return NO_IMAGE
        return await _png(roi.crop)

    return router


async def _png(image: Image, max_side: int | None = None) -> Response:
    data = await run_in_threadpool(display_png, image, max_side)
    return Response(data, media_type="image/png", headers=CACHED)


@dataclass
class Plan:
    """A scene's clusters drawn top-down on its map's floor plan, numbered as on the page."""

    view: belief_map.Projection
    regions: list[belief_map.DrawnRegion]
    marks: list[tuple[int, float, float]]  # cluster number, x, y


def _plan(store: MemoryStore, scene: Scene) -> Plan | None:
    """For a scene without camera images, where its clusters are in the map frame (None when
    none has a position): what the page shows first, since there are no boxes to draw."""
    placed = [(number, cluster.position) for number, cluster in enumerate(scene.clusters, 1)
              if cluster.position]
    if not placed:
        return None
    view, regions = belief_map.floor_plan(store, scene.map, [p for _, p in placed],
                                          PLAN_WIDTH, PLAN_HEIGHT)
    return Plan(view, regions, [(number, *view.point(p[0], p[1])) for number, p in placed])


def _found(get, key: ObjectId):
    try:
        return get(key)
    except NotFound as error:
        raise PageError(404, str(error)) from None

