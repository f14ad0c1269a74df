"""Who may talk to the app (README: Security). A pure ASGI middleware in front of every route,
so that it also answers requests no route takes:

- a Host header not in PMEM_ALLOWED_HOSTS gets 400, so that a site which points its own name
  at this server (DNS rebinding) is not served. (Starlette's TrustedHostMiddleware does the
  same with a plain-text error; ours keeps the app's JSON error shape.)
- a request under /api other than GET, HEAD or OPTIONS, whether it writes (POST /api/scenes)
  or asks a query in a JSON body, gets 403 when it comes from a page of another origin
  (`Origin`, PMEM_ALLOWED_ORIGINS excepted; `Origin: null` is a file:// or sandboxed page),
  and a POST 415 without `Content-Type: application/json` (or `application/x-ndjson`, scenes
  one a line, for POST /api/scenes). Any page may POST text/plain, form data or a body
  without type to any server without asking first; these types, like any other method (PUT,
  DELETE, ...: no route takes them, so they get 405), need the server's consent (a CORS
  preflight), which this app never gives.
- every response says `Referrer-Policy: no-referrer` and `X-Content-Type-Options: nosniff`.

`served_settings` is what `pmem serve` and `pmem demo` run with: beyond loopback without
PMEM_TOKEN, writes need a token made up for the run.
"""

from __future__ import annotations

import ipaddress
import secrets
import sys

from starlette.datastructures import Headers, MutableHeaders
from starlette.requests import Request
from starlette.responses import Response
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from percept_memory.memory.settings import Settings

from .errors import ApiError, error_response

LOOPBACK_HOSTS = "127.0.0.1,localhost,::1"
SAFE_METHODS = {"GET", "HEAD", "OPTIONS"}  # HTTP's "safe" methods: they change nothing
HEADERS = {"Referrer-Policy": "no-referrer", "X-Content-Type-Options": "nosniff"}
JSON = "application/json"
NDJSON = "application/x-ndjson"
BODY_TYPES = {"/api/scenes": (JSON, NDJSON)}  # the paths that take more than JSON


class Guard:
    """The checks above, for `app.add_middleware(Guard, settings=settings)`."""

    def __init__(self, app: ASGIApp, settings: Settings):
        self.app = app
        self.hosts = names(settings.allowed_hosts or LOOPBACK_HOSTS)
        self.origins = names(settings.allowed_origins)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":  # lifespan; the app has no WebSocket routes
            await self.app(scope, receive, send)
            return

        async def send_with_headers(message: Message) -> None:
            if message["type"] == "http.response.start":
                headers = MutableHeaders(scope=message)
                for name, value in HEADERS.items():
                    headers.setdefault(name, value)
            await send(message)

        refusal = self.refusal(scope)
        if refusal is not None:
            await refusal(scope, receive, send_with_headers)
        else:
            await self.app(scope, receive, send_with_headers)

    def refusal(self, scope: Scope) -> Response | None:
        """The error a request gets instead of an answer, or None if it may go on."""
        headers = Headers(scope=scope)
        host = headers.get("host", "")
        if host_name(host) not in self.hosts:
            return error_response(400, f"this server does not answer for the host {host!r}; "
                                       "PMEM_ALLOWED_HOSTS lists those it does")
        method, path = scope["method"], scope["path"]
        if method in SAFE_METHODS or not path.startswith("/api/"):
            return None
        origin = headers.get("origin")
        if origin is not None and origin.lower() not in {f"{scope['scheme']}://{host}".lower(),
                                                         *self.origins}:
            return error_response(403, f"pages from {origin} may not send {method} requests "
                                       "to this API; PMEM_ALLOWED_ORIGINS lists other origins "
                                       "that may")
        content_type = headers.get("content-type")
        types = BODY_TYPES.get(path, (JSON,))
        if method == "POST" and media_type(content_type) not in types:
            return error_response(415, f"{method} {path} takes Content-Type: "
                                       f"{' or '.join(types)}, "
                                       f"not {content_type or 'a body without one'}")
        return None


CHALLENGE = {"WWW-Authenticate": 'Bearer realm="percept-memory writes"'}  # RFC 6750


def authorise(request: Request, token: str | None) -> None:
    """Let a write through when it carries the write token, or none is configured."""
    if token is None:
        return
    given = request.headers.get("authorization", "")
    if not given:
        raise ApiError(401, "this server needs a write token: send Authorization: Bearer <token>",
                       headers=CHALLENGE)
    scheme, _, value = given.partition(" ")
    if scheme.lower() != "bearer" or not value.strip():
        raise ApiError(401, "the write token goes after the scheme: send Authorization: "
                            "Bearer <token>", headers=CHALLENGE)  # (what came is not echoed)
    if not secrets.compare_digest(value.encode(), token.encode()):
        raise ApiError(403, "the write token is not valid")


def media_type(content_type: str | None) -> str:
    """The media type of a Content-Type header, without its parameters: `application/json`."""
    return (content_type or "").partition(";")[0].strip().lower()


def names(setting: str) -> set[str]:
    """The entries of a comma-separated setting, in lower case."""
    return {name.strip().lower() for name in setting.split(",") if name.strip()}


def host_name(host: str) -> str:
    """The name in a Host header, without the port: `[::1]:8000` -> `::1`."""
    name = host[1:].partition("]")[0] if host.startswith("[") else host.partition(":")[0]
    return name.lower()


def served_settings(settings: Settings, host: str) -> Settings:
    """The settings of a server listening on `host`. Unless PMEM_ALLOWED_HOSTS says otherwise
    it answers for that host and loopback's names. Beyond loopback without PMEM_TOKEN, anyone
    on the network could write: a token is made up and printed once on stderr instead."""
    update: dict[str, str] = {}
    if not settings.allowed_hosts:
        update["allowed_hosts"] = f"{LOOPBACK_HOSTS},{host}"
    if settings.token is None and not is_loopback(host):
        update["token"] = secrets.token_urlsafe(24)
        print(f"PMEM_TOKEN is unset and the server listens on {host}, beyond loopback: reads "
              "are open, writes need this token, made up for this run:\n"
              f"  Authorization: Bearer {update['token']}\n"
              "Set PMEM_TOKEN to choose one that outlives the run.", file=sys.stderr)
    return settings.model_copy(update=update)


def is_loopback(host: str) -> bool:
    """True for an address only this machine can reach (127.0.0.0/8, ::1, localhost)."""
    if host.lower() == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:  # a host name: it may resolve to anything
        return False
