"""The query API under /api: every query of queries.engine.QUERIES twice, as GET with a query
string and as POST with a JSON body, validated by the same model and answered by the same
plan. Errors take the app's one format: 422 for a query that is not valid (each problem
named), 404 for an unknown object or cluster, 413 for a body over the limit.
"""

# no `from __future__ import annotations`: FastAPI reads the generated endpoints' annotations

import typing
from typing import Annotated, Any

from fastapi import APIRouter, Body, Depends, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.exceptions import RequestValidationError
from pydantic import BaseModel, ValidationError
from starlette.exceptions import HTTPException

from percept_memory.memory.errors import NotFound
from percept_memory.queries.engine import QUERIES, QueryEngine
from percept_memory.queries.ops import QueryError
from percept_memory.queries.params import from_params, is_list

MAX_QUERY_BYTES = 64 * 1024
PATHS = {"annotation_stats": "stats/annotations", "cooccurrence": "stats/cooccurrence",
         "timings": "stats/timings"}


def query_router(engine: QueryEngine) -> APIRouter:
    router = APIRouter(prefix="/api", tags=["queries"])
    for name, (model, plan) in QUERIES.items():
        _add_routes(router, getattr(engine, name), model, plan,
                    "/" + PATHS.get(name, name.replace("_", "-")))
    return router


def _add_routes(router: APIRouter, run, model: type[BaseModel], plan, path: str) -> None:
    answer = typing.get_args(typing.get_type_hints(plan)["return"])[-1]
    doc = (plan.__doc__ or "").strip()
    summary = doc.split("\n\n")[0].split(". ")[0].replace("\n", " ")

    async def answer_query_string(request: Request) -> Any:
        try:
            query = from_params(model, request.query_params.multi_items())
        except ValidationError as error:
            raise RequestValidationError(error.errors(include_url=False)) from None
        return await run_in_threadpool(_answered, run, query)

    async def answer_json_body(query: Annotated[model, Body()],  # type: ignore[valid-type]
                               _: Annotated[None, Depends(small_body)]) -> Any:
        return await run_in_threadpool(_answered, run, query)

    router.add_api_route(path, answer_query_string, methods=["GET"], response_model=answer,
                         summary=summary, description=doc,
                         openapi_extra={"parameters": query_parameters(model)},
                         operation_id=f"get_{path.strip('/').replace('/', '_')}")
    router.add_api_route(path, answer_json_body, methods=["POST"], response_model=answer,
                         summary=f"{summary} (JSON body)", description=doc,
                         operation_id=f"post_{path.strip('/').replace('/', '_')}")


def _answered(run, query: BaseModel) -> Any:
    try:
        return run(query)
    except NotFound as error:
        raise HTTPException(404, str(error)) from None
    except QueryError as error:
        raise HTTPException(422, str(error)) from None


def small_body(request: Request) -> None:
    declared = request.headers.get("content-length")
    if declared is not None and declared.isdigit() and int(declared) > MAX_QUERY_BYTES:
        raise HTTPException(413, f"a query body is at most {MAX_QUERY_BYTES} bytes")


def query_parameters(model: type[BaseModel]) -> list[dict]:
    """The query-string parameters of a model, for the OpenAPI description."""
    return [{"name": name, "in": "query", "required": info.is_required(),
             "description": (info.description or "") + (" (repeatable)" if is_list(model, name)
                                                          else ""),
             "schema": {"type": "string"}}
            for name, info in model.model_fields.items()]
