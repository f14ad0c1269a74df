"""Find more like this (queries/similar.py) over HTTP: GET /api/similar with a query string
(from a cluster or an object), POST /api/similar with a JSON body (also from an uploaded
crop, base64: its size is checked before it is decoded), and the /similar page, where every
crop of the cluster page leads: the crops found, best first, each with its similarity and a
link to look for more like it.
"""

# no `from __future__ import annotations`: FastAPI reads the endpoints' annotations

from typing import Annotated
from urllib.parse import urlencode

from fastapi import APIRouter, Body, Depends, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.exceptions import RequestValidationError
from fastapi.responses import HTMLResponse
from pydantic import ValidationError
from starlette.exceptions import HTTPException

from percept_memory.memory.errors import NotFound
from percept_memory.memory.store import MemoryStore
from percept_memory.queries.ops import QueryError
from percept_memory.queries.params import from_params
from percept_memory.queries.similar import (
    MAX_IMAGE_BYTES,
    Similarity,
    SimilarPage,
    SimilarQuery,
)

from .errors import READ_ERRORS, WRITE_ERRORS
from .html import PageError, page, problems
from .queries import query_parameters
from .search import with_crops

MAX_BODY = MAX_IMAGE_BYTES * 4 // 3 + 64 * 1024  # the crop in base64 and the rest


def routes(store: MemoryStore, similarity: Similarity) -> APIRouter:
    router = APIRouter()

    def answered(query: SimilarQuery) -> SimilarPage:
        try:
            return similarity.similar_to(query)
        except NotFound as error:
            raise HTTPException(404, str(error)) from None
        except QueryError as error:
            raise HTTPException(422, str(error)) from None

    @router.get("/api/similar", tags=["queries"], responses=READ_ERRORS,
                summary="The observations that look most like a cluster or an object",
                openapi_extra={"parameters": query_parameters(SimilarQuery)})
    async def similar_by_query_string(request: Request) -> SimilarPage:
        """Clusters ranked by how alike they look (the mean, over the descriptors both have,
        of each descriptor's cosine), within the filters. `image` goes in a JSON body."""
        try:
            query = from_params(SimilarQuery, request.query_params.multi_items())
        except ValidationError as error:
            raise RequestValidationError(error.errors(include_url=False)) from None
        if query.image is not None:
            raise HTTPException(422, "image: send it in a JSON body (POST /api/similar)")
        return await run_in_threadpool(answered, query)

    @router.post("/api/similar", tags=["queries"], responses=WRITE_ERRORS,
                 summary="The observations that look most like a cluster, an object or a "
                         "crop (JSON body)")
    async def similar_by_json_body(query: Annotated[SimilarQuery, Body()],
                                   _: Annotated[None, Depends(small_body)]) -> SimilarPage:
        """As GET /api/similar; `image` is a PNG or JPEG file in base64 (at most
        MAX_IMAGE_BYTES, 4 MiB, and 4 million pixels, read from its header)."""
        return await run_in_threadpool(answered, query)

    @router.get("/similar", include_in_schema=False, response_class=HTMLResponse)
    async def similar_page(request: Request) -> HTMLResponse:
        asked = [(k, v) for k, v in request.query_params.multi_items() if v.strip()]
        try:
            query = from_params(SimilarQuery, asked)
            if query.image is not None:
                raise QueryError("image: upload it with POST /api/similar")
            found = await run_in_threadpool(similarity.similar_to, query)
        except ValidationError as error:
            raise PageError(422, "; ".join(problems(error))) from None
        except QueryError as error:
            raise PageError(422, str(error)) from None
        except NotFound as error:
            raise PageError(404, str(error)) from None
        rest = [(k, v) for k, v in asked if k not in ("cluster", "object")]
        return page(request, "similar.html", {
            "found": found, "query": query,
            "crops": await run_in_threadpool(with_crops, store, found.items),
            "more": {h.id: "/similar?" + urlencode([("cluster", str(h.id)), *rest])
                     for h in found.items}})

    return router


def small_body(request: Request) -> None:
    """Refuse a body over MAX_BODY by its declared length, before it is read."""
    declared = request.headers.get("content-length")
    if declared is not None and declared.isdigit() and int(declared) > MAX_BODY:
        raise HTTPException(413, f"a similarity query's body is at most {MAX_BODY} bytes")
