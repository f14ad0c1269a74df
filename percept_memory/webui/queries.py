"""The query API under /api: every query of queries.engine.QUERIES twice, as GET with a query
string and as POST with a JSON body, validated by the same model and answered by the same
plan. Errors take the app's one format: 422 for a query that is not valid (each problem
named), 404 for an unknown object or cluster, 413 for a body over the limit.
"""

# no `from __future__ import annotations`: FastAPI reads the generated endpoints' annotations

import typing
from typing import Annotated, Any
from urllib.parse import quote

from fastapi import APIRouter, Body, Depends, Request, Response
from fastapi.concurrency import run_in_threadpool
from fastapi.exceptions import RequestValidationError
from pydantic import BaseModel, ValidationError
from starlette.exceptions import HTTPException

from percept_memory.memory.errors import NotFound
from percept_memory.queries.engine import QUERIES, QueryEngine, rebuilding_for
from percept_memory.queries.ops import QueryError
from percept_memory.queries.params import from_params, is_list

from .errors import READ_ERRORS, WRITE_ERRORS

MAX_QUERY_BYTES = 64 * 1024
# on a belief's answer read while a map's belief was being rebuilt: which maps (README)
REBUILDING_HEADER = "X-Belief-Rebuilding"
PATHS = {"annotation_stats": "stats/annotations", "cooccurrence": "stats/cooccurrence",
         "timings": "stats/timings", "annotator_report": "annotators",
         "annotator_clusters": "annotators/clusters"}


def query_router(engine: QueryEngine) -> APIRouter:
    router = APIRouter(prefix="/api", tags=["queries"])
    for name, (model, plan) in QUERIES.items():
        _add_routes(router, engine, name, model, plan,
                    "/" + PATHS.get(name, name.replace("_", "-")))
    return router


def _add_routes(router: APIRouter, engine: QueryEngine, name: str, model: type[BaseModel], plan,
                path: str) -> None:
    answer = typing.get_args(typing.get_type_hints(plan)["return"])[-1]
    doc = (plan.__doc__ or "").strip()
    summary = doc.split("\n\n")[0].split(". ")[0].replace("\n", " ")
    run = getattr(engine, name)

    def rebuilt(query: BaseModel) -> list[str]:
        return rebuilding_for(engine.runner.db, name, query)

    async def answer_query_string(request: Request, response: Response) -> Any:
        try:
            query = from_params(model, request.query_params.multi_items())
        except ValidationError as error:
            raise RequestValidationError(error.errors(include_url=False)) from None
        return await run_in_threadpool(_answered, run, rebuilt, query, response)

    async def answer_json_body(query: Annotated[model, Body()],  # type: ignore[valid-type]
                               _: Annotated[None, Depends(small_body)],
                               response: Response) -> Any:
        return await run_in_threadpool(_answered, run, rebuilt, query, response)

    router.add_api_route(path, answer_query_string, methods=["GET"], response_model=answer,
                         summary=summary, description=doc, responses=READ_ERRORS,
                         openapi_extra={"parameters": query_parameters(model)},
                         operation_id=f"get_{path.strip('/').replace('/', '_')}")
    router.add_api_route(path, answer_json_body, methods=["POST"], response_model=answer,
                         summary=f"{summary} (JSON body)", description=doc,
                         responses=WRITE_ERRORS,
                         operation_id=f"post_{path.strip('/').replace('/', '_')}")


def _answered(run, rebuilt, query: BaseModel, response: Response) -> Any:
    """The answer; one read from a belief while its map was being rebuilt (as it began or
    ended) says so in REBUILDING_HEADER: the maps, percent-encoded, comma-separated."""
    maps = set(rebuilt(query))
    try:
        answer = run(query)
    except NotFound as error:  # (an object not in a belief being made again: it may come)
        raise HTTPException(404, str(error), headers=_rebuilding(maps)) from None
    except QueryError as error:
        raise HTTPException(422, str(error)) from None
    response.headers.update(_rebuilding(maps | set(rebuilt(query))))
    return answer


def _rebuilding(maps: set[str]) -> dict[str, str]:
    return {REBUILDING_HEADER: ",".join(quote(m, safe="") for m in sorted(maps))} if maps else {}


def small_body(request: Request) -> None:
    declared = request.headers.get("content-length")
    if declared is not None and declared.isdigit() and int(declared) > MAX_QUERY_BYTES:
        raise HTTPException(413, f"a query body is at most {MAX_QUERY_BYTES} bytes")


def query_parameters(model: type[BaseModel]) -> list[dict]:
    """The query-string parameters of a model, for the OpenAPI description."""
    properties = model.model_json_schema()["properties"]
    return [{"name": name, "in": "query", "required": info.is_required(),
             "description": (info.description or "") + (" (repeatable)" if is_list(model, name)
                                                          else ""),
             "schema": parameter_schema(properties[name], is_list(model, name))}
            for name, info in model.model_fields.items()]


PLAIN_TYPES = {"integer", "number", "boolean", "string"}
PLAIN_KEYWORDS = {"type", "enum", "minimum", "maximum", "minLength", "maxLength", "pattern",
                  "default"}
ANNOTATIONS = {"title", "description"}  # said by the parameter itself


def parameter_schema(field: dict, repeatable: bool) -> dict:
    """The schema of a parameter as the query string gives it: a number, flag, choice or
    word is typed as such; a time, box, sphere, point or predicate is text in the form its
    description gives (e.g. x0,y0,z0,x1,y1,z1), read by the model's validators."""
    arms = [arm for arm in field.get("anyOf", [field]) if arm.get("type") != "null"]
    value = arms[0] if len(arms) == 1 else {}
    if repeatable:
        value = value.get("items", {})
    plain = value.get("type") in PLAIN_TYPES and set(value) <= PLAIN_KEYWORDS | ANNOTATIONS
    schema = {k: v for k, v in value.items() if k in PLAIN_KEYWORDS} if plain else {
        "type": "string"}
    return {"type": "array", "items": schema} if repeatable else schema
