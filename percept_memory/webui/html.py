"""What every HTML page shares: the Jinja2 templates, the response with its security headers,
the error page, and the parsing of URL parameters (each bad one refused with a 404 or 422 page
naming it, never a 500).

Every page sends a Content-Security-Policy that allows nothing but this site's own images and
style sheet; the live page, the playback page, the 3D views (`view=3d`) and the API page
(Swagger UI) alone may also run this site's scripts (files, never inline) and fetch from it, a
scene page with images its viewer script. No page sends a Referer to the links it leads to.
Jinja2 escapes every value, so OCR text, web results and annotator logs are shown, never run.
"""

from __future__ import annotations

import re
from pathlib import Path
from urllib.parse import quote

from bson import ObjectId
from fastapi import Request
from fastapi.responses import HTMLResponse
from fastapi.templating import Jinja2Templates
from pydantic import TypeAdapter, ValidationError
from pymongo.errors import OperationFailure

from percept_memory.memory.types import Correction
from percept_memory.memory.types.curation import in_force, verdict
from percept_memory.queries.model import Time

from . import render

HERE = Path(__file__).parent


def content_security_policy(**allowed: str) -> str:
    """This site's Content-Security-Policy, with the directives named (as script_src=...) set."""
    directives = {"default-src": "'none'", "img-src": "'self'", "style-src": "'self'",
                  "form-action": "'self'", "base-uri": "'none'", "frame-ancestors": "'none'"}
    directives.update({name.replace("_", "-"): value for name, value in allowed.items()})
    return "; ".join(f"{name} {value}" for name, value in directives.items())


CSP = content_security_policy()
SCRIPT_CSP = content_security_policy(script_src="'self'", connect_src="'self'")
"""The policy of a page that runs this site's own scripts (static files, never inline)."""
VIEWER_CSP = content_security_policy(script_src="'self'")
"""The policy of a scene page with images: its viewer script runs, and fetches nothing."""
API_DOCS_CSP = content_security_policy(script_src="'self'", connect_src="'self'",
                                       img_src="'self' data:")
"""The policy of the API page (/docs): Swagger UI draws its icons from data: URLs."""
LIST_FIELDS = {"timestamp": 1, "robot": 1, "time": 1, "summary": 1, "clusters": 1,
               # the names of the scene's images, not their pixels
               "images": {"$map": {"input": {"$objectToArray": {"$ifNull": ["$images", {}]}},
                                   "in": "$$this.k"}}}
"""What the lists of scenes read of a scene (macros.html: scene_row)."""

templates = Jinja2Templates(directory=HERE / "templates")  # autoescapes .html templates
templates.env.filters["time"] = render.time_of
templates.env.filters["cut"] = render.cut
# a name as one segment of a URL's path: a /, .. or ? in it stays in it (an image named
# ../../api/export?... was a request of every viewer's browser to another path)
templates.env.filters["segment"] = lambda text: quote(str(text), safe="")
templates.env.globals.update(type_name=render.type_name, shown_fields=render.shown_fields,
                             open_fields=render.OPEN_FIELDS, in_force=in_force, verdict=verdict)
templates.env.tests["correction"] = lambda a: isinstance(a, Correction)


class PageError(Exception):
    """A request a page cannot answer: shown as an HTML error page with this status."""

    def __init__(self, status: int, message: str, problems: list[str] | None = None):
        super().__init__(message)
        self.status, self.message, self.problems = status, message, problems or []


MAX_OFFERED = 1000  # values a form offers to choose from


def offered(collection, key: str) -> list[str]:
    """The values stored under `key` (an index's distinct keys), as a form offers them: at
    most MAX_OFFERED. Names are short (types.Name), but one answer of distinct holds at most
    16 MB: past that the form offers none rather than fail (a page that answered 500 for good
    after 17 scenes of 1 MiB regions, before names were capped)."""
    try:
        values = collection.distinct(key)
    except OperationFailure:
        return []
    return sorted(v for v in values if v)[:MAX_OFFERED]


def page(request: Request, template: str, context: dict, status: int = 200,
         policy: str = CSP) -> HTMLResponse:
    return templates.TemplateResponse(request, template, context, status_code=status,
                                      headers=headers(policy))


def headers(policy: str = CSP) -> dict[str, str]:
    return {"Content-Security-Policy": policy}  # nosniff and the rest: guard.py, on all


def parse_id(text: str, kind: str) -> ObjectId:
    if not ObjectId.is_valid(text):
        raise PageError(404, f"no {kind} {text!r}: ids are 24 hexadecimal digits")
    return ObjectId(text)


def nanoseconds(text: str, name: str) -> int:
    """An ISO 8601 date or time (UTC unless it says otherwise), or nanoseconds since the epoch,
    as nanoseconds since the epoch."""
    try:
        return TIME.validate_python(text)  # (the query model's reading: the API's)
    except ValidationError:
        raise PageError(422, f"{name}: {text!r} is not a date or time such as "
                             "2024-05-06T08:30, or nanoseconds") from None


TIME = TypeAdapter(Time)


def problems(error: ValidationError, whole: str = "query") -> list[str]:
    """A page's parameters' validation problems, one line each: `field: problem` (`whole` for
    one of all of them)."""
    return [f"{'.'.join(map(str, e['loc'])) or whole}: {e['msg']}"
            for e in error.errors(include_url=False)]


def nanoseconds_through(text: str, name: str) -> int:
    """The first nanosecond after the moment `text` names, to the precision it is written
    in: "until 08:30" is until 08:30 has passed (a form's time field gives minutes or
    seconds, a bar of the histogram milliseconds), "until 2024-05-06" the whole day."""
    start = nanoseconds(text, name)
    if text.strip().isdigit():
        return start + 1
    clock = CLOCK.search(text)
    if clock is None:  # a date
        return start + 86_400 * 10**9
    minutes, seconds, fraction = clock.groups()
    if fraction:  # in milli-, micro- or nanoseconds (a browser writes .31 for .310)
        return start + 10 ** (9 - 3 * -(-len(fraction) // 3))
    return start + 10**9 * (1 if seconds else 60 if minutes else 3600)


CLOCK = re.compile(r"[T ]\d\d(:\d\d)?(:\d\d)?(?:[.,](\d{1,9}))?")
LOCAL_TIME = re.compile(r"^\d{4}-\d\d-\d\dT\d\d:\d\d(:\d\d(\.\d{1,3})?)?$")


def time_input_type(value: str) -> str:
    """A time field's input type: a browser's date and time picker, or text for a value the
    picker cannot hold (nanoseconds, a time zone, a mistake): it would show it blank, and the
    next submit would drop the filter the page is showing."""
    return "datetime-local" if not value or LOCAL_TIME.match(value) else "text"


def bounded_int(text: str, name: str, low: int, high: int) -> int:
    """A whole number from the URL within [low, high]."""
    if not (text.isascii() and text.strip().isdigit()) or not low <= int(text) <= high:
        raise PageError(422, f"{name}: {text!r} is not a whole number from {low} to {high}")
    return int(text)
