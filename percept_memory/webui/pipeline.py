"""The pipeline page: how far each map's belief is (the newest scene consolidated, the scenes
pending and held, a rebuild under way, which process consolidates it) and the held scenes with
their errors. The same report as `pmem pipeline` and GET /api/pipeline (memory/pipeline.py)."""

from __future__ import annotations

from fastapi import APIRouter, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import HTMLResponse

from percept_memory.memory.pipeline import status
from percept_memory.memory.store import MemoryStore

from .html import page


def routes(store: MemoryStore) -> APIRouter:
    router = APIRouter(include_in_schema=False, default_response_class=HTMLResponse)

    @router.get("/pipeline")
    async def pipeline_page(request: Request) -> HTMLResponse:
        return page(request, "pipeline.html", await run_in_threadpool(status, store))

    return router
