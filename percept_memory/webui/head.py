"""HEAD answered as GET without its body (RFC 9110, 9.3.2: the same headers, no content).
FastAPI's routes take only the methods they declare, so a HEAD of a page or of a GET endpoint
was a 405; a `curl -I` or a link checker must see what a GET would."""

from __future__ import annotations

from starlette.types import ASGIApp, Message, Receive, Scope, Send


class HeadAsGet:
    """The app, with a HEAD request run as its GET and the body left out."""

    def __init__(self, app: ASGIApp):
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope["method"] != "HEAD":
            await self.app(scope, receive, send)
            return

        ended = False

        async def headers_only(message: Message) -> None:
            """The response ends with its headers: a stream (the live page's events, an
            export) is not waited for, and ends when its client's disconnect is seen."""
            nonlocal ended
            if ended:
                return
            await send(message)
            if message["type"] == "http.response.start":
                await send({"type": "http.response.body", "body": b"", "more_body": False})
                ended = True

        await self.app({**scope, "method": "GET"}, receive, headers_only)
