"""The enrichment page: the lookup queue per state, the failed jobs with their last error, the
latest lookups (backend, answered by the cache or the service, hash distance, latency) and how
often the perceptual-hash cache answered (DESIGN.md: Ingest and enrichment; thesis 5.4.5).
The same report as `pmem jobs` and GET /api/jobs (ingest/jobs.py: job_report)."""

from __future__ import annotations

from fastapi import APIRouter, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import HTMLResponse

from percept_memory.ingest.jobs import STATES, job_report
from percept_memory.memory.schema import JOBS, LOOKUP_CACHE
from percept_memory.memory.store import MemoryStore

from .html import page

FAILED_SHOWN = 50
LOOKUPS_SHOWN = 30
HIT_WINDOW = 1000  # the cache hit rate is over this many latest lookups


def routes(store: MemoryStore) -> APIRouter:
    router = APIRouter(include_in_schema=False, default_response_class=HTMLResponse)

    @router.get("/enrichment")
    async def enrichment_page(request: Request) -> HTMLResponse:
        return page(request, "enrichment.html",
                    {**await run_in_threadpool(enrichment_report, store), "states": STATES})

    return router


def enrichment_report(store: MemoryStore) -> dict:
    failed = job_report(store, "failed", FAILED_SHOWN)
    done = job_report(store, "done", LOOKUPS_SHOWN)
    (cache,) = list(store.db[JOBS].aggregate([
        {"$match": {"state": "done"}},
        {"$sort": {"updated": -1}},
        {"$limit": HIT_WINDOW},
        {"$group": {"_id": None, "lookups": {"$sum": 1},
                    "hits": {"$sum": {"$cond": ["$outcome.cached", 1, 0]}},
                    "fresh_ms": {"$avg": {"$cond": ["$outcome.cached", None,
                                                    "$outcome.latency_ms"]}},
                    "cached_ms": {"$avg": {"$cond": ["$outcome.cached", "$outcome.latency_ms",
                                                     None]}}}},
    ])) or [{"lookups": 0, "hits": 0, "fresh_ms": None, "cached_ms": None}]
    return {"counts": failed["counts"], "failed": failed["jobs"], "lookups": done["jobs"],
            "cache": {**cache, "entries": store.db[LOOKUP_CACHE].estimated_document_count()}}
