"""Lookup backends: services that say what a cluster's crop shows (thesis 5.3-5.4).

A backend has a `name` (results are cached per name) and `async lookup(crop) -> [Finding]`,
the crop a BGR uint8 array; it raises BackendError for a failure worth retrying (timeout,
connection refused, 5xx) and RejectedLookup for one that is not (the service refused this
crop). Three ship: `simulated` (the thesis' Goggles timings and answers, for demos and
benchmarks), `catalogue` (a local folder of product images matched by pHash and ORB features)
and `http` (any JSON lookup service). `open_backend` picks one by name from the settings.
"""

from __future__ import annotations

from typing import Annotated, Literal, Protocol

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from percept_memory.ingest.errors import BackendSetupError
from percept_memory.memory.settings import Settings

Category = Literal[
    "text", "logo", "similar_image", "product", "user_submitted", "barcode", "other"
]
"""The result categories of thesis table 5.3."""

Coordinate = Annotated[float, Field(ge=0)]


class Finding(BaseModel):
    """One result of a lookup (thesis figure 5.1): a category and a title (the text read, the
    brand, the product name, the barcode digits, ...), the region of the crop it concerns
    (x, y, width, height in crop pixels), links, and for products their brand and key-values."""

    model_config = ConfigDict(extra="forbid")

    category: Category
    title: str = Field(min_length=1)
    box: tuple[Coordinate, Coordinate, Coordinate, Coordinate] | None = None
    links: list[str] = []
    brand: str | None = None
    properties: dict[str, str | bool | int | float] = {}


class BackendError(Exception):
    """The lookup failed in a way another attempt may not (timeout, refused, server error)."""


class RejectedLookup(BackendError):
    """The service refused the request for good (bad request, no such endpoint): no retry."""


class LookupBackend(Protocol):
    name: str

    async def lookup(self, crop: np.ndarray) -> list[Finding]: ...

    async def aclose(self) -> None: ...


def open_backend(settings: Settings, name: str | None = None) -> LookupBackend:
    """The backend called `name` (default: PMEM_LOOKUP_BACKEND), configured from settings."""
    name = name or settings.lookup_backend
    if name == "simulated":
        from .simulated import SimulatedService

        return SimulatedService(seed=settings.simulated_seed)
    if name == "catalogue":
        from .catalogue import ProductCatalogue

        return ProductCatalogue.load(settings.catalogue_dir)
    if name == "http":
        from .http_json import HttpLookup

        if not settings.lookup_url:
            raise BackendSetupError("the http lookup backend needs PMEM_LOOKUP_URL")
        return HttpLookup(settings.lookup_url, timeout_s=settings.lookup_timeout_s,
                          retries=settings.lookup_retries, authorization=settings.lookup_auth)
    raise BackendSetupError(f"unknown lookup backend {name!r}: simulated, catalogue or http")
