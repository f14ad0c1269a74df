"""The FastAPI app. Every error is one JSON shape: {"error": {"status", "message", "problems"}}.

Writes need `Authorization: Bearer <PMEM_TOKEN>` when a token is configured; guard.py decides
who may send requests at all (Host, Origin, JSON bodies only). Request bodies are read in chunks
and refused with 413 as soon as they pass PMEM_MAX_REQUEST_MB.
"""

from __future__ import annotations

from collections.abc import Callable
from contextlib import asynccontextmanager
from typing import Annotated, Any, Literal

from fastapi import FastAPI, Query, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.exceptions import RequestValidationError
from fastapi.responses import HTMLResponse, JSONResponse
from pymongo.errors import AutoReconnect
from starlette.exceptions import HTTPException
from starlette.requests import ClientDisconnect
from starlette.routing import Match

from percept_memory.ingest.jobs import State, job_report
from percept_memory.ingest.json_batches import NotScenes
from percept_memory.ingest.service import IngestError, IngestService, memory_pipeline
from percept_memory.memory.errors import StoreError
from percept_memory.memory.pipeline import status as pipeline_status
from percept_memory.memory.settings import Settings
from percept_memory.memory.store import MemoryStore
from percept_memory.memory.types import Scene
from percept_memory.queries.engine import QueryEngine
from percept_memory.queries.similar import Similarity

from . import curation, review, similar
from .catalogue import catalogue_router
from .errors import (
    READ_ERRORS,
    UNAVAILABLE,
    WRITE_ERRORS,
    ApiError,
    error_response,
    store_status,
)
from .export_api import export_router
from .guard import JSON, NDJSON, Guard, authorise, media_type
from .head import HeadAsGet
from .html import API_DOCS_CSP, page
from .pages import mount_pages
from .queries import query_router
from .records import records_router
from .scene3d import cloud_router


def allowed(app: FastAPI, request: Request) -> set[str]:
    """The methods the routes of the request's path take (Starlette's 405 names the first
    route's: /api/clusters takes GET and POST)."""
    return {method for method in METHODS for route in app.router.routes
            if route.matches({**request.scope, "method": method})[0] == Match.FULL}


METHODS = ("GET", "POST", "PUT", "PATCH", "DELETE")


def create_app(store: MemoryStore, settings: Settings) -> FastAPI:
    """The app on a store; one IngestService serves every write. The app runs the memory
    pipeline in a thread while it serves (unless settings.consolidator is off), and keeps its
    similarity index current in another from the first similarity search on."""
    pipeline = memory_pipeline(store, settings)
    similarity = Similarity(store, settings, in_background=True)

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        if settings.consolidator:
            pipeline.start()
        try:
            yield
        finally:
            pipeline.stop()
            similarity.close()
            service.close()

    app = FastAPI(
        lifespan=lifespan,
        title="percept-memory",
        description="Long-term spatio-temporal memory for robot perception.",
        version="0.1.0",
        docs_url=None,  # served below with the Swagger UI in static/swagger: no CDN
        redoc_url=None,
    )
    app.add_middleware(Guard, settings=settings)  # who may talk to the app: guard.py
    app.add_middleware(HeadAsGet)  # (head.py)
    service = IngestService(store, pipeline=pipeline, settings=settings)
    max_bytes = int(settings.max_request_mb * 2**20)
    scene_schema = Scene.model_json_schema()
    mount_pages(app, store, settings)  # the HTML pages (pages.py)

    @app.exception_handler(ApiError)
    async def _api_error(request: Request, error: ApiError) -> JSONResponse:
        return error_response(error.status, error.message, error.problems, error.headers)

    @app.exception_handler(StoreError)
    async def _store_error(request: Request, error: StoreError) -> JSONResponse:
        return error_response(store_status(error), str(error))

    @app.exception_handler(AutoReconnect)  # no server to select, or a connection lost
    async def _unavailable(request: Request, error: AutoReconnect) -> JSONResponse:
        return error_response(503, UNAVAILABLE)

    @app.exception_handler(HTTPException)
    async def _http_error(request: Request, error: HTTPException) -> JSONResponse:
        headers = error.headers
        if error.status_code == 405:  # every route of the path, not only the first one's
            headers = {**(headers or {}), "Allow": ", ".join(sorted(allowed(app, request)))}
        return error_response(error.status_code, str(error.detail), headers=headers)

    @app.exception_handler(RequestValidationError)
    async def _request_error(request: Request, error: RequestValidationError) -> JSONResponse:
        problems = [{"path": ".".join(map(str, e["loc"])), "message": e["msg"]}
                    for e in error.errors()]
        return error_response(422, "the request is not valid", problems)

    @app.get("/docs", include_in_schema=False)
    def api_docs(request: Request) -> HTMLResponse:
        return page(request, "docs.html", {"openapi_url": app.openapi_url}, policy=API_DOCS_CSP)

    @app.get("/api/schema/scene", summary="JSON Schema of a scene (interchange format v1)",
             responses=READ_ERRORS)
    def scene_json_schema() -> dict[str, Any]:
        return scene_schema

    @app.post("/api/scenes", status_code=201, summary="Store one scene or a batch of scenes",
              responses=WRITE_ERRORS, openapi_extra=scenes_body())
    async def post_scenes(
        request: Request,
        wait: Annotated[Literal["belief"] | None, Query(
            description="`belief`: answer once the new scenes are consolidated into the "
                        "belief (at most PMEM_BELIEF_WAIT_S); `belief` in the answer says "
                        "whether they were: current, pending, or held (a scene of their "
                        "maps is held: GET /api/pipeline)")] = None,
    ) -> dict[str, Any]:
        """Body: a scene, or a list of scenes, as GET /api/schema/scene describes; or, as
        `application/x-ndjson`, scenes one a line (blank lines skipped; a large batch is made
        ready faster, each line being parsed alone). A batch is validated whole and stored in
        one transaction, with its place in the memory pipeline: the answer comes once the
        scenes are durably stored; identity consolidation and lookups follow (see GET
        /api/pipeline), unless `wait=belief`. Scenes stored before (same robot and timestamp)
        keep their ids and come back with `created: false`."""
        authorise(request, settings.token)
        ndjson = media_type(request.headers.get("content-type")) == NDJSON

        def stored_and_settled() -> tuple[list, str | None]:
            """In one worker thread: the consolidator is asked for the scenes as soon as they
            are stored, not after a turn of the event loop. The belief's state after."""
            results = service.ingest_json(body, ndjson=ndjson)  # (the consolidator waits)
            if not wait:
                return results, None
            if service.settled(results, settings.belief_wait_s):
                return results, "current"
            ids = [r.scene_id for r in results]
            return results, "held" if service.pipeline.held(ids) else "pending"

        body = await _read_body(request, max_bytes, service.pipeline.arriving)
        try:
            results, belief = await run_in_threadpool(stored_and_settled)
        except NotScenes as error:
            raise ApiError(422, str(error)) from None
        except IngestError as error:
            raise ApiError(422, "the scenes are not valid", error.problems) from None
        answer: dict[str, Any] = {"belief": belief} if wait else {}
        return {**answer, "scenes": [
            {"scene_id": str(r.scene_id), "cluster_ids": [str(c) for c in r.cluster_ids],
             "annotation_ids": [[str(a) for a in ids] for ids in r.annotation_ids],
             "created": r.created}
            for r in results
        ]}

    app.include_router(query_router(QueryEngine(store, settings)))
    app.include_router(export_router(store, settings))
    app.include_router(cloud_router(store))
    app.include_router(records_router(store))
    app.include_router(catalogue_router(store))
    app.include_router(similar.routes(store, similarity))
    app.include_router(curation.routes(store, settings))
    app.include_router(review.routes(store))

    @app.get("/api/pipeline", summary="How far the belief of each map is",
             responses=READ_ERRORS)
    def pipeline_report() -> dict[str, Any]:
        """Per map: `consolidated_until` (the time in ns of the newest scene consolidated into
        its belief), the scenes `pending` and `held` (a stage kept failing; the `held` list
        gives their errors), whether it is `rebuilding` and which process consolidates it."""
        return pipeline_status(store)

    @app.get("/api/jobs", summary="The enrichment queue: jobs per state, the latest jobs",
             responses=READ_ERRORS)
    def list_jobs(state: State | None = None,
                  limit: Annotated[int, Query(ge=0, le=1000)] = 50) -> dict[str, Any]:
        """Counts per state (queued, running, done, failed) and the `limit` most recently
        updated jobs (of `state`, if given; `limit=0`: the counts alone): attempts, worker,
        the last error of a failed job, the outcome of a done one (backend, cached or fresh,
        hash distance, latency)."""
        return job_report(store, state, limit)

    with_scene_schemas(app)
    return app


SCENE_REF = "#/components/schemas/{model}"


def scenes_body() -> dict:
    """The OpenAPI request body of POST /api/scenes: a scene or a non-empty list of them. (The
    route reads its body itself, to refuse a large one early; see with_scene_schemas.)"""
    scene = {"$ref": SCENE_REF.format(model="Scene")}
    return {"requestBody": {"required": True, "content": {
        JSON: {"schema": {"oneOf": [scene, {"type": "array", "items": scene, "minItems": 1}]}},
        NDJSON: {"schema": {"type": "string", "description": "scenes one a line, each a JSON "
                            "object as in application/json; blank lines are skipped"}}}}}


def with_scene_schemas(app: FastAPI) -> None:
    """Put the scene's JSON Schema and its parts among the OpenAPI description's schemas, where
    the body of POST /api/scenes refers to them."""
    scene = Scene.model_json_schema(ref_template=SCENE_REF)
    parts = {**scene.pop("$defs", {}), "Scene": scene}
    describe = app.openapi

    def openapi() -> dict[str, Any]:
        description = describe()
        schemas = description.setdefault("components", {}).setdefault("schemas", {})
        clashes = {name for name in parts if schemas.get(name, parts[name]) != parts[name]}
        assert not clashes, f"two OpenAPI schemas are named {clashes}"
        schemas.update(parts)
        return description

    app.openapi = openapi  # type: ignore[method-assign]


async def _read_body(request: Request, max_bytes: int,
                     arriving: Callable[[], None]) -> bytes:
    """The body, refused past `max_bytes`; `arriving()` after each part that came."""
    declared = request.headers.get("content-length")
    if declared is not None and declared.isdigit() and int(declared) > max_bytes:
        raise ApiError(413, f"the request body is over the limit of {max_bytes} bytes")
    chunks, size = [], 0
    try:
        async for chunk in request.stream():
            size += len(chunk)
            if size > max_bytes:
                raise ApiError(413, f"the request body is over the limit of {max_bytes} bytes")
            chunks.append(chunk)
            arriving()
    except ClientDisconnect:  # (no one to answer: said in one line, not a traceback)
        raise ApiError(400, "the client went away before the body ended") from None
    return b"".join(chunks)



