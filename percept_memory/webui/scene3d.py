"""The 3D views, an addition to the scene page and the map page (`view=3d`), drawn by
static/view3d.js with three.js: a scene's points, cluster boxes and camera frustum, or a map's
regions and the objects believed there at the page's moment. The page hands the shapes over in
a JSON data block (data, never run); the points, too many for a page, come from
GET /api/scenes/{scene_id}/cloud as binary, at most queries.scene3d.MAX_POINTS of them.
"""

from __future__ import annotations

from typing import Annotated

from bson import ObjectId
from fastapi import APIRouter, Query
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import Response

from percept_memory.memory.store import MemoryStore
from percept_memory.memory.types import Scene
from percept_memory.queries import scene3d
from percept_memory.queries.results import ObjectAt

from .errors import READ_ERRORS
from .html import PageError
from .records import SCENE_ID

BINARY = {"content": {"application/octet-stream": {}}, "description": (
    "N points: N little-endian float32 triples x, y, z (metres, in the scene's frame), then N "
    "uint8 triples red, green, blue; N is in the X-Points header")}


def wanted(view: str) -> bool:
    """Whether the URL asks for the 3D view (`view=3d`); an unknown view is refused."""
    if view not in ("", "2d", "3d"):
        raise PageError(422, f"view: {view!r} is not 2d or 3d")
    return view == "3d"


def cloud_router(store: MemoryStore) -> APIRouter:
    router = APIRouter(prefix="/api", tags=["scenes"])

    @router.get("/scenes/{scene_id}/cloud", response_class=Response,
                summary="A scene's points, as binary for a 3D viewer",
                responses={200: BINARY, **READ_ERRORS})
    async def scene_cloud(
        scene_id: Annotated[str, SCENE_ID],
        max_points: Annotated[int, Query(ge=1, le=scene3d.MAX_POINTS, description=(
            "at most this many points, an even sample of them"))] = scene3d.MAX_POINTS,
    ) -> Response:
        """The scene's clouds, else its depth image seen from its camera, else its clusters'
        own points, in the scene's frame: at most `max_points` of them, the same sample on
        every request. Colours are the sensor's, grey where it gave none."""
        scene = await run_in_threadpool(store.get_scene, ObjectId(scene_id))
        xyz, rgb = await run_in_threadpool(scene3d.points, scene, max_points)
        return Response(xyz.astype("<f4").tobytes() + rgb.tobytes(),
                        media_type="application/octet-stream",
                        headers={"X-Points": str(len(xyz)), "Cache-Control": "max-age=3600"})

    return router


def scene_view(scene: Scene, names: dict) -> dict:
    """What view3d.js draws of a scene: its points (by URL), boxes labelled as on the page
    (number and object name) and its camera's frustum."""
    shapes = scene3d.shapes(scene)
    label = {number: f"{number}. {names.get(c.object_id) or c.region or 'cluster'}"
             for number, c in enumerate(scene.clusters, 1)}
    return {"frame": shapes.frame, "points": shapes.points,
            "cloud": f"/api/scenes/{scene.id}/cloud" if shapes.points else None,
            "boxes": [{"low": b.low, "high": b.high, "label": label[b.number]}
                      for b in shapes.boxes],
            "frustum": shapes.frustum}


def map_view(regions: dict[str, tuple[list[float], list[float]]],
             objects: list[ObjectAt]) -> dict:
    """What view3d.js draws of a map: its regions' boxes and the objects believed at the
    moment, each with its name and state (present, hidden)."""
    return {"frame": "map", "boxes": [{"low": low, "high": high, "label": name, "region": True}
                                      for name, (low, high) in regions.items()],
            "objects": [{"position": o.position, "label": o.name or "?", "state": o.state}
                        for o in objects if o.position is not None]}
