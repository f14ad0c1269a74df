"""The long-term catalogue over HTTP: which objects this home has, and whether an observation's
object was seen before (queries/catalogue.py), as JSON and as the catalogue page."""

from __future__ import annotations

import math
from typing import Annotated, Any

from bson import ObjectId
from fastapi import APIRouter, Query, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import HTMLResponse

from percept_memory.memory.catalogue.stage import CatalogueStage
from percept_memory.memory.store import MemoryStore
from percept_memory.queries import catalogue

from .errors import READ_ERRORS
from .html import bounded_int, page
from .records import CLUSTER_ID

DRAWING_PX = 72
CHANGES_SHOWN = 30


def ring_drawing(graph: dict, size: float = DRAWING_PX) -> dict:
    """An entry's partial models on a ring (at most a few: a complete graph stays readable),
    each a disc as large as its observation was long, and its links as lines as thick as the
    models are alike; in SVG user units."""
    models = graph["models"]
    centre, radius = size / 2, size / 2 - 12 if len(models) > 1 else 0.0
    longest = max((m["length"] for m in models), default=1) or 1
    at = {}
    for i, m in enumerate(models):
        angle = 2 * math.pi * i / max(len(models), 1) - math.pi / 2
        at[m["model"]] = {"model": m["model"], "x": round(centre + radius * math.cos(angle), 1),
                          "y": round(centre + radius * math.sin(angle), 1),
                          "r": round(4 + 5 * m["length"] / longest, 1)}
    lines = [{"a": at[link["a"]], "b": at[link["b"]], "weight": link["weight"],
              "width": round(0.5 + 4 * link["weight"], 1)}
             for link in graph["links"] if link["a"] in at and link["b"] in at]
    return {"size": size, "models": list(at.values()), "links": lines}


def catalogue_router(store: MemoryStore) -> APIRouter:
    """The API's routes and the page's."""
    router = APIRouter()
    router.include_router(_api(store))

    @router.get("/catalogue", include_in_schema=False, response_class=HTMLResponse)
    async def catalogue_page(request: Request, map: str | None = None, limit: str = "100",
                             offset: str = "0") -> HTMLResponse:
        limit = bounded_int(limit, "limit", 1, 1000)  # (a page's own 422, not the API's JSON)
        offset = bounded_int(offset, "offset", 0, 10**9)
        (found, total), changes = await run_in_threadpool(
            lambda: (catalogue.page(store, map or None, limit, offset),
                     catalogue.history(store, map or None, CHANGES_SHOWN)))
        for entry in found:
            entry["drawing"] = ring_drawing(entry["graph"])
        return page(request, "catalogue.html", {
            "entries": found, "changes": changes, "map_name": map, "total": total,
            "offset": offset, "limit": limit})

    return router


def _api(store: MemoryStore) -> APIRouter:
    router = APIRouter(prefix="/api/catalogue", tags=["catalogue"])
    stage = CatalogueStage(store)  # each map's learner, read again when its catalogue changed

    @router.get("", summary="The objects this home has (the catalogue's entries)",
                responses=READ_ERRORS)
    async def entries(
        map: Annotated[str | None, Query(description="only this map's entries")] = None,
        limit: Annotated[int, Query(ge=1, le=1000)] = 100,
        offset: Annotated[int, Query(ge=0, description="entries skipped, the most seen")] = 0,
    ) -> dict[str, Any]:
        """`total` entries, `limit` of them after the first `offset`. Each entry is an object
        learnt from its views, the most seen first: `views` (the
        clusters its models began with, the longest look first), `names`, the belief `objects`
        whose tracks it gathers, `times_seen` (how often they were seen, shared with the other
        entries holding their models), where it is `now`
        (the one seen last) and its `graph`: its partial models and the similarity links
        between them."""
        found, total = await run_in_threadpool(catalogue.page, store, map, limit, offset)
        return {"total": total, "entries": found}

    @router.get("/history", summary="The catalogue's entries that merged or split",
                responses=READ_ERRORS)
    async def history(
        map: Annotated[str | None, Query(description="only this map's changes")] = None,
        limit: Annotated[int, Query(ge=1, le=1000)] = 50,
    ) -> dict[str, Any]:
        """The newest first: `kind` (merged: several entries `before`, one `after`; split: one
        before, the entries it went to after), the scene `time` (ns), the `cluster_id` whose
        learning did it, and which entries after are `current` (a later change may undo one)."""
        return {"changes": await run_in_threadpool(catalogue.history, store, map, limit)}

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
