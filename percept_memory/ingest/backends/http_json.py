"""A client for any HTTP JSON lookup service.

Request: POST to the service URL with `{"image": {"jpeg": <base64>, "encoding": "bgr8"},
"width": w, "height": h}` (the image as the interchange format carries one) and, when
PMEM_LOOKUP_AUTH is set, that value as the Authorization header.
Answer: `{"results": [{"category", "title", "box", "links", "brand", "properties"}, ...]}`
(Finding's fields; box in crop pixels).

Connection errors, timeouts, 429 and 5xx answers are retried at once a few times (0.1 s, 0.2 s,
... apart), then raised as BackendError so the job is retried later with backoff; any other 4xx
is RejectedLookup (the job fails at once, keeping the service's message), as is an answer of
more than MAX_ANSWER_BYTES.
"""

from __future__ import annotations

import asyncio
import base64

import cv2
import httpx2
import numpy as np
from pydantic import BaseModel, ValidationError

from . import BackendError, Finding, RejectedLookup

RETRY_PAUSE_S = 0.1
JPEG_QUALITY = 90
MAX_ANSWER_BYTES = 4 * 2**20  # findings take a few kB: far more is a broken service


class Answer(BaseModel):
    results: list[Finding]


class HttpLookup:
    """The HTTP JSON lookup client; one connection pool per worker process."""

    name = "http"

    def __init__(self, url: str, *, timeout_s: float, retries: int,
                 authorization: str | None = None):
        self.url = url
        self.retries = retries
        headers = {"Authorization": authorization} if authorization else {}
        self.client = httpx2.AsyncClient(timeout=timeout_s, headers=headers)

    async def lookup(self, crop: np.ndarray) -> list[Finding]:
        ok, jpeg = cv2.imencode(".jpg", crop, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
        if not ok:
            raise RejectedLookup("the crop could not be encoded as JPEG")
        body = {"image": {"jpeg": base64.b64encode(jpeg.tobytes()).decode(), "encoding": "bgr8"},
                "width": crop.shape[1], "height": crop.shape[0]}
        for attempt in range(self.retries + 1):
            try:
                async with self.client.stream("POST", self.url, json=body) as response:
                    content = await _bounded(response, self.url)
            except httpx2.TransportError as error:  # connection refused, reset, timed out
                problem = f"{type(error).__name__} from {self.url}: {error}".rstrip(": ")
            else:
                if response.status_code < 400:
                    return _findings(content, self.url)
                problem = (f"HTTP {response.status_code} from {self.url}: "
                           f"{content[:200].decode(errors='replace')}")
                if response.status_code < 500 and response.status_code != 429:
                    raise RejectedLookup(problem)
            if attempt < self.retries:
                await asyncio.sleep(RETRY_PAUSE_S * 2**attempt)
        raise BackendError(problem)

    async def aclose(self) -> None:
        await self.client.aclose()


async def _bounded(response: httpx2.Response, url: str) -> bytes:
    """The answer's body, read no further than MAX_ANSWER_BYTES: a broken or hostile service
    streaming without end would otherwise fill the worker's memory (a job is failed)."""
    declared = response.headers.get("content-length", "")
    if declared.isdigit() and int(declared) > MAX_ANSWER_BYTES:
        raise RejectedLookup(f"the answer of {url} is {int(declared):,} bytes, more than "
                             f"{MAX_ANSWER_BYTES:,}")
    content = bytearray()
    async for chunk in response.aiter_bytes():
        content += chunk
        if len(content) > MAX_ANSWER_BYTES:
            raise RejectedLookup(f"the answer of {url} is more than {MAX_ANSWER_BYTES:,} bytes")
    return bytes(content)


def _findings(content: bytes, url: str) -> list[Finding]:
    try:
        return Answer.model_validate_json(content).results
    except ValidationError as error:
        problems = "; ".join(f"{'.'.join(map(str, e['loc']))}: {e['msg']}"
                             for e in error.errors(include_url=False)[:3])
        raise BackendError(f"the answer of {url} is not valid: {problems}") from None
