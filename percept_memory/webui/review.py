"""The review queue page (queries/review.py) and its JSON twin: the doubtful clusters of the
latest scenes, the most doubtful first, each with a relabel form; after a relabel the next
row's field takes the focus (static/curate.js), so a person corrects one after another from the
keyboard. Corrected clusters leave the queue and are counted as fixed.
"""

# no `from __future__ import annotations`: FastAPI reads the endpoints' annotations

from typing import Annotated, Any

from fastapi import APIRouter, Query, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import HTMLResponse

from percept_memory.memory.store import MemoryStore
from percept_memory.queries.review import (
    DEFAULT_SHOWN,
    DEFAULT_WINDOW,
    MAX_SHOWN,
    MAX_WINDOW,
    Doubt,
    review_queue,
)

from .curation import as_json
from .errors import READ_ERRORS
from .html import SCRIPT_CSP, bounded_int, page


def routes(store: MemoryStore) -> APIRouter:
    router = APIRouter()

    @router.get("/review", include_in_schema=False, response_class=HTMLResponse)
    async def review_page(request: Request, scenes: str = str(DEFAULT_WINDOW),
                          shown: str = str(DEFAULT_SHOWN), robot: str = "") -> HTMLResponse:
        window = bounded_int(scenes, "scenes", 1, MAX_WINDOW)
        count = bounded_int(shown, "shown", 1, MAX_SHOWN)
        queue = await run_in_threadpool(review_queue, store, window, count, robot or None)
        return page(request, "review.html", {
            "queue": queue, "window": window, "shown": count, "robot": robot,
            "max_window": MAX_WINDOW}, policy=SCRIPT_CSP)

    @router.get("/api/review", summary="The review queue: the most doubtful clusters first",
                tags=["corrections"], responses=READ_ERRORS)
    def review(scenes: Annotated[int, Query(ge=1, le=MAX_WINDOW)] = DEFAULT_WINDOW,
               shown: Annotated[int, Query(ge=1, le=MAX_SHOWN)] = DEFAULT_SHOWN,
               robot: Annotated[str | None, Query(max_length=200)] = None) -> dict[str, Any]:
        """Over the latest `scenes` scenes (of `robot`): clusters whose annotators disagree
        (`disagreement`: the share of the names' weight the heaviest name lacks) or whose
        identity decision had a close alternative (`closeness`: one minus the margin), ranked
        by the larger (`score`); `fixed`: the window's clusters a person corrected."""
        queue = review_queue(store, scenes, shown, robot)
        return {"scenes": queue.scenes, "clusters": queue.clusters, "fixed": queue.fixed,
                "doubts": [described(d) for d in queue.doubts]}

    return router


def described(doubt: Doubt) -> dict[str, Any]:
    return as_json({**doubt.__dict__, "score": doubt.score,
                    "names": [{"name": n, "weight": w} for n, w in doubt.names]})
