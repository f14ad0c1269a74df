"""What was stored, read back by id as JSON: a scene or a cluster in the interchange format
(docs/interchange.md), with the ids it was given, what enrichment and people appended since
(`arrived` says how many came with it) and the object identity linked it to."""

from __future__ import annotations

from typing import Annotated, Any

from bson import ObjectId
from fastapi import APIRouter, Path
from fastapi.concurrency import run_in_threadpool

from percept_memory.memory.store import MemoryStore

from .errors import READ_ERRORS

SCENE_ID = Path(pattern="^[0-9a-f]{24}$", description="the scene's id (24 hexadecimal digits)")
CLUSTER_ID = Path(pattern="^[0-9a-f]{24}$", description="the cluster's id (24 hexadecimal digits)")


def records_router(store: MemoryStore) -> APIRouter:
    router = APIRouter(prefix="/api", tags=["scenes"])

    @router.get("/scenes/{scene_id}", summary="A stored scene, as JSON", responses=READ_ERRORS)
    async def scene(scene_id: Annotated[str, SCENE_ID]) -> dict[str, Any]:
        """The scene as stored, in the interchange format (images as base64 PNG or JPEG):
        posted again, it is the same scene (`created: false`)."""
        found = await run_in_threadpool(store.get_scene, ObjectId(scene_id))
        return found.model_dump(mode="json", by_alias=True)

    @router.get("/clusters/{cluster_id}", summary="A stored cluster, as JSON",
                responses=READ_ERRORS)
    async def cluster(cluster_id: Annotated[str, CLUSTER_ID]) -> dict[str, Any]:
        """The cluster as stored, in the interchange format, with its `scene_id` and the
        `object_id` identity believes it shows."""
        found = await run_in_threadpool(store.get_cluster, ObjectId(cluster_id))
        return found.model_dump(mode="json", by_alias=True)

    return router
