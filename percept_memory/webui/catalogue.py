"""The long-term catalogue over HTTP: which objects this home has, and whether an observation's
object was seen before (queries/catalogue.py), as JSON and as the catalogue page."""

from __future__ import annotations

from typing import Annotated, Any

from bson import ObjectId
from fastapi import APIRouter, Path, Query, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import HTMLResponse

from percept_memory.memory.catalogue.stage import CatalogueStage
from percept_memory.memory.store import MemoryStore
from percept_memory.queries import catalogue

from .errors import READ_ERRORS
from .html import page

CLUSTER_ID = Path(pattern="^[0-9a-f]{24}$", description="the cluster's id (24 hexadecimal digits)")


def catalogue_router(store: MemoryStore) -> APIRouter:
    """The API's routes and the page's."""
    router = APIRouter()
    router.include_router(_api(store))

    @router.get("/catalogue", include_in_schema=False, response_class=HTMLResponse)
    async def catalogue_page(request: Request, map: str | None = None,
                             limit: Annotated[int, Query(ge=1, le=1000)] = 100
                             ) -> HTMLResponse:
        found = await run_in_threadpool(catalogue.entries, store, map or None, limit)
        return page(request, "catalogue.html", {"entries": found, "map_name": map})

    return router


def _api(store: MemoryStore) -> APIRouter:
    router = APIRouter(prefix="/api/catalogue", tags=["catalogue"])
    stage = CatalogueStage(store)  # each map's learner, read again when its catalogue changed

    @router.get("", summary="The objects this home has (the catalogue's entries)",
                responses=READ_ERRORS)
    async def entries(
        map: Annotated[str | None, Query(description="only this map's entries")] = None,
        limit: Annotated[int, Query(ge=1, le=1000)] = 100,
    ) -> dict[str, Any]:
        """Each entry is an object learnt from its views, the most seen first: `views` (the
        clusters its models began with, the longest look first), `names`, the belief `objects`
        whose tracks it gathers, `times_seen` (how often they were seen) and where it is
        `now` (the one seen last)."""
        return {"entries": await run_in_threadpool(catalogue.entries, store, map, limit)}

    @router.get("/graph", summary="The catalogue's similarity graph of a map",
                responses=READ_ERRORS)
    async def graph(
        map: Annotated[str, Query(description="the map")],
        limit: Annotated[int, Query(ge=1, le=100_000)] = 10_000,
    ) -> dict[str, Any]:
        """Its partial `models` (each named by the cluster it began with, with its `entry`)
        and the `links` kept between them with their weight; an entry is a connected
        component."""
        return await run_in_threadpool(catalogue.similarity_graph, store, map, limit)

    @router.get("/seen-before/{cluster_id}", summary="Have we seen this object before?",
                responses=READ_ERRORS)
    async def seen_before(
        cluster_id: Annotated[str, CLUSTER_ID],
        limit: Annotated[int, Query(ge=1, le=100)] = 5,
    ) -> dict[str, Any]:
        """The entries the cluster's object may be, best first: `inclusion`, the share of the
        cluster's views the entry holds, and `consensus`, how far its kinds of evidence agree
        that this entry is the best match."""
        ranked = await run_in_threadpool(catalogue.seen_before, store, ObjectId(cluster_id),
                                         limit, stage)
        return {"cluster_id": cluster_id, "entries": ranked}

    return router
