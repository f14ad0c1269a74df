"""The search page: clusters (observations) by text, regions, robots, a sphere or a box in the
map frame or the k nearest to a point, a time range and annotation field predicates, in one
GET form whose fields are the query model's (queries/model.py: ClusterQuery), so the URL holds
the query, can be shared, and `/search?text=cereal&region=table` asks what
`/api/clusters?text=cereal&region=table` does. Results show as a grid of crops or as a list, a
page at a time by the engine's cursor (the k nearest: one page). A query the model refuses
comes back as the form with each problem named (422), never a 500. Each region and robot
offered shows how many observations it would select with the rest of the query, and the labels
and objects most frequent among the matches are offered as links with theirs (facets.py).
"""

from __future__ import annotations

import asyncio
from urllib.parse import urlencode

from fastapi import APIRouter, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import HTMLResponse, RedirectResponse
from pydantic import ValidationError

from percept_memory.converters import registered_types
from percept_memory.memory.search_keys import normal_label
from percept_memory.memory.store import MemoryStore
from percept_memory.memory.types import Annotation
from percept_memory.queries.engine import QueryEngine
from percept_memory.queries.model import MAX_K, ClusterQuery
from percept_memory.queries.ops import QueryError, QueryTimeout
from percept_memory.queries.params import from_params

from .facets import cluster_facet_counts, shown
from .html import PageError, offered, page, problems, time_input_type

PAGE_SIZE = 48
VIEWS = ("grid", "list")
HINT_SKIPPED = {"id", "source"}


def routes(store: MemoryStore, engine: QueryEngine) -> APIRouter:
    router = APIRouter(include_in_schema=False, default_response_class=HTMLResponse)

    @router.get("/search", response_model=None)
    async def search_page(request: Request) -> HTMLResponse | RedirectResponse:
        asked_for = request.query_params.multi_items()
        given = [(k, v) for k, v in asked_for if v.strip()]
        if len(given) < len(asked_for):  # the form sends its empty fields too
            return RedirectResponse("/search?" + urlencode(given), status_code=303)
        views = [v for k, v in given if k == "view"]
        view = views[-1] if views else VIEWS[0]
        if view not in VIEWS:
            raise PageError(422, f"view: {view!r} is not one of {', '.join(VIEWS)}")
        asked = [(k, v) for k, v in given if k != "view"]
        context = {"view": view, "form": _form(asked), "time_inputs": _time_inputs(asked),
                   "problems": [], "hits": [],
                   "crops": set(), "links": _links(asked, view), "next": None,
                   "counts": {}, "narrowing": [], "uncounted": 0, "shown": shown,
                   **await run_in_threadpool(_choices, store)}
        try:
            query = from_params(ClusterQuery, asked if any(k == "limit" for k, _ in asked)
                                else [*asked, ("limit", str(PAGE_SIZE))])
            # the page and the counts beside its filters at once (each its own commands):
            # the page waits for the slower, not for their sum
            found, counts = await asyncio.gather(
                run_in_threadpool(engine.clusters, query),
                run_in_threadpool(cluster_facet_counts, engine.runner, store.clusters, query,
                                  {"region": context["regions"], "robot": context["robots"]})
                if query.near is None else _nothing())  # (the k nearest are not counted)
        except ValidationError as error:
            context["problems"] = problems(error)
            return page(request, "search.html", context, 422)
        except QueryTimeout as error:
            context["problems"] = [f"{error}: narrow the search"]
            return page(request, "search.html", context, 503)
        except QueryError as error:
            context["problems"] = [str(error)]
            return page(request, "search.html", context, 422)
        context.update(hits=found.items, total=found.total, export=_exported(asked),
                       crops=await run_in_threadpool(with_crops, store, found.items))
        context.update(counts=counts, narrowing=await run_in_threadpool(
            _narrowing, store, asked, view, counts), uncounted=sum(
            n is None for values in counts.values() for n in values.values()))
        if found.next:
            rest = [(k, v) for k, v in asked if k != "cursor"]
            context["next"] = "/search?" + urlencode([*rest, ("cursor", found.next),
                                                      ("view", view)])
        return page(request, "search.html", context)

    return router


async def _nothing() -> dict:
    return {}


def _form(asked: list[tuple[str, str]]) -> dict[str, list[str]]:
    """The values given for each field, to fill the form in again."""
    form: dict[str, list[str]] = {}
    for key, value in asked:
        form.setdefault(key, []).append(value)
    return form


def _time_inputs(asked: list[tuple[str, str]]) -> dict[str, str]:
    """The input type of each time field (html.time_input_type)."""
    given = dict(asked)
    return {name: time_input_type(given.get(name, "")) for name in ("after", "before")}


def _links(asked: list[tuple[str, str]], view: str) -> dict[str, str]:
    """The same search shown each way, and from its first page."""
    rest = [(k, v) for k, v in asked if k != "cursor"]
    links = {name: "/search?" + urlencode([*asked, ("view", name)]) for name in VIEWS}
    links["first"] = "/search?" + urlencode([*rest, ("view", view)])
    return links


def _narrowing(store: MemoryStore, asked: list[tuple[str, str]], view: str,
               counts: dict[str, dict]) -> list[dict]:
    """The label and object facets: each value offered (facets.py: the chosen and the most
    frequent) with its count and the link that adds it to the search, or takes it out when
    it is chosen."""
    rest = [(k, v) for k, v in asked if k != "cursor"]
    names = {o["_id"]: o.get("name") for o in store.objects.find(
        {"_id": {"$in": list(counts.get("object", {}))}}, {"name": 1})}
    facets = []
    for name, title in (("labelled", "Labels"), ("object", "Objects")):
        same = normal_label if name == "labelled" else str  # (a label as it is stored)
        chosen = {same(v) for k, v in rest if k == name}
        values = []
        for value, count in counts.get(name, {}).items():
            text, on = str(value), str(value) in chosen
            link = ([(k, v) for k, v in rest if k != name or same(v) != text]
                    if on else [*rest, (name, text)])
            shown = (f"{names.get(value) or 'unnamed'} ({text[-6:]})" if name == "object"
                     else text)
            values.append({"text": shown, "count": count, "chosen": on,
                           "link": "/search?" + urlencode([*link, ("view", view)])})
        if values:
            facets.append({"name": name, "title": title, "offered": values})
    return facets


def _exported(asked: list[tuple[str, str]]) -> list[tuple[str, str]] | None:
    """The filter of the search, for the export form: everything but paging, order and k (an
    export takes every match, oldest first); None for the k nearest to a point, a ranking
    an export does not take."""
    if any(k == "near" for k, _ in asked):
        return None
    return [(k, v) for k, v in asked if k not in ("cursor", "sort", "limit", "k")]


def _choices(store: MemoryStore) -> dict:
    """What the form offers: the regions and robots stored (index scans), and examples of
    predicates on the registered annotation types' fields."""
    predicates = sorted(
        f"{cls.__name__.casefold()}:{field}="
        for cls in registered_types().values() if issubclass(cls, Annotation)
        for field in cls.model_fields if field not in HINT_SKIPPED)
    return {"regions": offered(store.clusters, "search.region"),
            "robots": offered(store.clusters, "search.robot"),
            "predicates": predicates, "max_k": MAX_K}


def with_crops(store: MemoryStore, hits: list) -> set:
    """The ids of the hits that have an image crop to show."""
    found = store.clusters.find({"_id": {"$in": [h.id for h in hits]},
                                 "hypotheses": {"$elemMatch": {"crop": {"$ne": None}}}}, {"_id": 1})
    return {doc["_id"] for doc in found}
