"""The annotators page, for whoever debugs an annotator (DESIGN.md, user 3): over the latest
scenes (a window the URL sets: how many, of which robot, up to when), per annotator how many
annotations it made, how often it ran, its mean, 95th percentile and longest time, its
warnings and errors; its times and its warning and error rates hour by hour as charts
(annotator_charts.py); the latest error lines; and confusion tables of the classes annotators
gave against each other and against the ground truth, each cell a link to the list of the
clusters behind it. The numbers come from queries/annotators.py, as GET /api/annotators and
/api/annotators/clusters give them.
"""

from __future__ import annotations

from urllib.parse import urlencode

from fastapi import APIRouter, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import HTMLResponse
from pydantic import BaseModel, ValidationError

from percept_memory.memory.store import MemoryStore
from percept_memory.queries.annotators import GROUND_TRUTH, PEOPLE
from percept_memory.queries.engine import QueryEngine
from percept_memory.queries.model import MAX_WINDOW, AnnotatorWindow, ConfusionCell
from percept_memory.queries.ops import QueryError, QueryTimeout
from percept_memory.queries.params import from_params

from .annotator_charts import charts, confusion_table
from .html import PageError, page, problems


def routes(store: MemoryStore, engine: QueryEngine) -> APIRouter:
    router = APIRouter(include_in_schema=False, default_response_class=HTMLResponse)

    @router.get("/annotators")
    async def annotators_page(request: Request) -> HTMLResponse:
        window = _query(AnnotatorWindow, request)
        report = await run_in_threadpool(_answered, engine.annotator_report, window)
        # the cells' links hold the window's newest scene, so they list what was counted
        fixed = window.model_copy(update={"before": report.last}) if report.last else window
        return page(request, "annotators.html", {
            "report": report, "charts": charts(report), "confusion_table": confusion_table,
            "window": window,
            "ground_truth": GROUND_TRUTH, "people": PEOPLE, "max_window": MAX_WINDOW,
            "cell_link": lambda comparison, count: "/annotators/clusters?" + urlencode(
                _params(fixed, annotator=comparison.annotator, reference=comparison.reference,
                        said=count.said, expected=count.expected)),
            # (a window not filled holds the oldest scene: nothing is earlier)
            "earlier": "/annotators?" + urlencode(_params(window, before=report.first - 1))
            if report.first and report.scenes >= window.scenes else None})

    @router.get("/annotators/clusters")
    async def cell_page(request: Request) -> HTMLResponse:
        cell = _query(ConfusionCell, request)
        found = await run_in_threadpool(_answered, engine.annotator_clusters, cell)
        return page(request, "annotator_cell.html", {
            "cell": cell, "found": found, "ground_truth": GROUND_TRUTH,
            "back": "/annotators?" + urlencode(_params(AnnotatorWindow(
                scenes=cell.scenes, robot=cell.robot, before=cell.before)))})

    return router


def _query(model: type[BaseModel], request: Request) -> BaseModel:
    """The query of the URL; the form's empty fields are left out."""
    try:
        return from_params(model, [(k, v) for k, v in request.query_params.multi_items()
                                   if v.strip()])
    except ValidationError as error:
        raise PageError(422, "these parameters are not valid", problems(error)) from None


def _answered(run, query: BaseModel):
    try:
        return run(query)
    except QueryTimeout as error:
        raise PageError(503, f"{error}: take fewer scenes") from None
    except QueryError as error:
        raise PageError(422, str(error)) from None


def _params(query: BaseModel, **changed) -> list[tuple[str, str]]:
    """A query as URL parameters, those not set left out."""
    values = {**query.model_dump(exclude_defaults=True), **changed}
    return [(k, str(v)) for k, v in values.items() if v is not None]
