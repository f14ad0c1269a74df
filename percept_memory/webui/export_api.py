"""GET and POST /api/export: the clusters a query selects, as training data in a zip that is
streamed while it is written. The query (format, label source, filter) is checked, and the
export run up to its first cluster, before the first byte is sent, so a bad query or one whose
clusters all have to be skipped gets the app's one error format (422 naming why), not a broken
or empty zip."""

# no `from __future__ import annotations`: FastAPI reads the endpoints' annotations

from typing import Annotated

from fastapi import APIRouter, Body, Depends, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.exceptions import RequestValidationError
from fastapi.responses import StreamingResponse
from pydantic import ValidationError
from starlette.exceptions import HTTPException

from percept_memory.memory.settings import Settings
from percept_memory.memory.store import MemoryStore
from percept_memory.queries.export.model import ExportQuery
from percept_memory.queries.export.run import Export, NothingExported
from percept_memory.queries.ops import QueryError
from percept_memory.queries.params import from_params

from .errors import READ_ERRORS, WRITE_ERRORS
from .html import PageError, problems
from .queries import query_parameters, small_body

DESCRIPTION = (ExportQuery.__doc__ or "") + (
    " Formats: coco (annotations.json + images/), yolo (images/, labels/, data.yaml), "
    "imagefolder (<label>/<cluster id>.png) and jsonl (features.jsonl); each with "
    "provenance.jsonl (scene, time, camera pose, region, annotator of the label) and "
    "manifest.json (counts, what was skipped and why). Same store and query, same bytes.")
ZIP = {200: {"content": {"application/zip": {}}, "description": "the export as a zip"}}


def export_router(store: MemoryStore, settings: Settings) -> APIRouter:
    router = APIRouter(tags=["export"])

    def started(query: ExportQuery) -> StreamingResponse:
        """The zip's response, its export run up to its first cluster (raises QueryError or
        NothingExported before any byte is sent)."""
        export = Export(store, query, settings)
        chunks = export.started()
        return StreamingResponse(
            chunks, media_type="application/zip",
            headers={"Content-Disposition": f'attachment; filename="pmem-{query.format}.zip"',
                     "X-Clusters-Selected": str(export.total)})

    def answered(query: ExportQuery) -> StreamingResponse:
        try:
            return started(query)
        except (QueryError, NothingExported) as error:
            raise HTTPException(422, str(error)) from None

    @router.get("/api/export", summary="Export training data (query string)",
                description=DESCRIPTION, response_class=StreamingResponse,
                responses={**ZIP, **READ_ERRORS},
                openapi_extra={"parameters": query_parameters(ExportQuery)})
    async def export_by_query_string(request: Request) -> StreamingResponse:
        try:
            query = form_query(request)
        except ValidationError as error:
            raise RequestValidationError(error.errors(include_url=False)) from None
        return await run_in_threadpool(answered, query)

    @router.get("/search/export", include_in_schema=False, response_model=None)
    async def export_from_the_search_page(request: Request) -> StreamingResponse:
        """The search page's export form: what it cannot export is a page naming why (with
        the way back), not the API's JSON."""
        try:
            query = form_query(request)
            return await run_in_threadpool(started, query)
        except ValidationError as error:
            raise PageError(422, f"not exported: {'; '.join(problems(error, 'export'))}"
                            ) from None
        except (QueryError, NothingExported) as error:
            raise PageError(422, f"not exported: {error}") from None

    @router.post("/api/export", summary="Export training data (JSON body)",
                 description=DESCRIPTION, response_class=StreamingResponse,
                 responses={**ZIP, **WRITE_ERRORS})
    async def export_by_json_body(query: Annotated[ExportQuery, Body()],
                                  _: Annotated[None, Depends(small_body)]) -> StreamingResponse:
        return await run_in_threadpool(answered, query)

    return router


def form_query(request: Request) -> ExportQuery:
    """The export the query string asks for; a blank value is an option left unset (as HTML
    forms send them)."""
    return from_params(ExportQuery, [(k, v) for k, v in request.query_params.multi_items()
                                     if v.strip()])
