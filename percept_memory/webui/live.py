"""The live page: the latest scenes, and new ones as they are stored, without reloading. A
MongoDB change stream on `scenes` feeds a server-sent event stream (/live/events, one `scene`
event per stored scene carrying its table row, rendered and escaped by the same template
macro as the scene log); live.js, a static file of this site, puts each row on top. The
event ids are the change stream's resume tokens, so a browser that reconnects (it sends the
last one as Last-Event-ID) misses nothing the oplog still holds. Without JavaScript the page
is the latest scenes with a refresh link.
"""

from __future__ import annotations

from collections.abc import AsyncIterator

from fastapi import APIRouter, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import HTMLResponse, StreamingResponse
from pymongo import DESCENDING
from pymongo.change_stream import ChangeStream
from pymongo.errors import PyMongoError

from percept_memory.memory.store import MemoryStore

from .html import LIST_FIELDS, SCRIPT_CSP, headers, page, templates

SHOWN = 20
WAIT_MS = 2000  # a poll of the change stream waits this long; then a keep-alive comment
MAX_TOKEN = 1000


def routes(store: MemoryStore) -> APIRouter:
    router = APIRouter(include_in_schema=False, default_response_class=HTMLResponse)

    @router.get("/live")
    async def live_page(request: Request) -> HTMLResponse:
        def load() -> list[dict]:
            return list(store.scenes.find({}, LIST_FIELDS).sort(
                [("timestamp", DESCENDING), ("_id", DESCENDING)]).limit(SHOWN))

        return page(request, "live.html", {"scenes": await run_in_threadpool(load),
                                           "shown": SHOWN}, policy=SCRIPT_CSP)

    @router.get("/live/events")
    async def live_events(request: Request) -> StreamingResponse:
        stream = await run_in_threadpool(_watch, store, request.headers.get("last-event-id"))
        return StreamingResponse(_events(store, stream, request), media_type="text/event-stream",
                                 headers={**headers(), "Cache-Control": "no-cache"})

    return router


def _watch(store: MemoryStore, resume: str | None) -> ChangeStream:
    """New scenes from now on, or from after the event the browser saw last."""
    pipeline = [{"$match": {"operationType": "insert"}}, {"$project": {"documentKey": 1}}]
    if resume and len(resume) <= MAX_TOKEN:
        try:
            return store.scenes.watch(pipeline, resume_after={"_data": resume},
                                      max_await_time_ms=WAIT_MS)
        except PyMongoError:  # not a token of ours, or gone from the oplog: from now on
            pass
    return store.scenes.watch(pipeline, max_await_time_ms=WAIT_MS)


async def _events(store: MemoryStore, stream: ChangeStream,
                  request: Request) -> AsyncIterator[str]:
    row = templates.get_template("macros.html").module.scene_row
    try:
        yield f"retry: {WAIT_MS}\n\n"
        while not await request.is_disconnected():
            change = await run_in_threadpool(stream.try_next)
            if change is None:
                yield ": waiting\n\n"
                continue
            scene = await run_in_threadpool(
                store.scenes.find_one, {"_id": change["documentKey"]["_id"]}, LIST_FIELDS)
            if scene is not None:
                data = "".join(f"data: {line}\n" for line in str(row(scene)).splitlines())
                yield f"event: scene\nid: {change['_id']['_data']}\n{data}\n"
    finally:
        await run_in_threadpool(stream.close)
