"""One lookup job: a cluster's crop -> the shared cache, else the backend -> annotations.

Every result becomes a WebLookup annotation (category, title, its box in the scene image, links
and provenance: backend, fresh or cached, hash distance, latency, job), followed by what it says
in the memory's own types where its category carries one (thesis 5.4.4): text -> Text, logo ->
Logo, product -> Product, barcode -> Barcode, so the object can be found by them. Annotation ids
derive from the job id and the position in the answer, and all of a job's annotations are
appended in one transaction by the store's idempotent append: a job run again (retried, or
taken over from a worker that died after appending) adds nothing the second time. The answer is
cached before it is appended, so a rerun finds the same answer, hence the same annotations.
"""

from __future__ import annotations

import asyncio
from dataclasses import dataclass
from time import perf_counter
from typing import Any

import cv2
import numpy as np

from percept_memory.ingest.backends import BackendError, Finding, LookupBackend
from percept_memory.ingest.jobs import Job
from percept_memory.ingest.lookup_cache import LookupCache
from percept_memory.ingest.phash import crop_phash
from percept_memory.memory.async_store import AsyncMemoryStore
from percept_memory.memory.types import (
    Annotation,
    Barcode,
    Box,
    Image,
    ImageROI,
    Logo,
    Product,
    Text,
    WebLookup,
)
from percept_memory.memory.types.annotations import LookupProvenance, lookup_annotation_id
from percept_memory.memory.types.base import as_name

SOURCE = "LookupWorker"


class NothingToLookUp(Exception):
    """The cluster has no crop a backend could take: the job cannot succeed."""


def bgr_crop(image: Image) -> np.ndarray:
    """The crop as the 8-bit BGR array backends take."""
    data = image.data
    if data.dtype != np.uint8:
        raise NothingToLookUp(f"the crop is {data.dtype}; lookups take 8-bit images")
    if data.ndim == 2 or data.shape[2] == 1:
        return cv2.cvtColor(data, cv2.COLOR_GRAY2BGR)
    if image.encoding.startswith("rgb"):
        return np.ascontiguousarray(data[..., 2::-1])
    return np.ascontiguousarray(data[..., :3])


def in_image(box: tuple | None, roi: ImageROI, crop_shape: tuple[int, ...]) -> Box | None:
    """A box in crop pixels as a box in the scene image the ROI was cut from (crops may have
    been scaled)."""
    if box is None:
        return None
    x, y, width, height = roi.box
    sx, sy = width / crop_shape[1], height / crop_shape[0]
    return (round(x + box[0] * sx), round(y + box[1] * sy), round(box[2] * sx),
            round(box[3] * sy))


def annotations_for(findings: list[Finding], provenance: LookupProvenance, roi: ImageROI,
                    crop_shape: tuple[int, ...]) -> list[Annotation]:
    """The annotations a lookup answer adds to its cluster, with their ids."""
    source = f"{SOURCE}:{provenance.backend}"
    out: list[Annotation] = []
    for finding in findings:
        box = in_image(finding.box, roi, crop_shape)
        out.append(WebLookup(source=source, service=provenance.backend,
                             category=finding.category, title=finding.title, box=box,
                             links=finding.links, provenance=provenance))
        if finding.category == "text":
            out.append(Text(source=source, text=finding.title, box=box))
        elif finding.category == "logo":
            out.append(Logo(source=source, brand=as_name(finding.title), box=box))
        elif finding.category == "product":
            out.append(Product(source=source, name=as_name(finding.title),
                               brand=finding.brand and as_name(finding.brand),
                               properties=finding.properties))
        elif finding.category == "barcode":
            symbology = "EAN-13" if len(finding.title) == 13 and finding.title.isdigit() else ""
            out.append(Barcode(source=source, code=finding.title, symbology=symbology))
    if provenance.job_id is not None:
        for position, annotation in enumerate(out):
            annotation.id = lookup_annotation_id(provenance.job_id, position)
    return out


@dataclass
class Lookup:
    """What running a lookup job takes: the memory, the shared cache, a backend, a time limit
    for one backend call."""

    store: AsyncMemoryStore
    cache: LookupCache
    backend: LookupBackend
    timeout_s: float

    async def run(self, job: Job) -> dict[str, Any]:
        """Look the job's cluster up and append the answer; returns the job's outcome."""
        cluster = await self.store.get_cluster(job.cluster_id)
        roi = cluster.hypothesis_of(ImageROI)
        if roi is None or roi.crop is None:
            raise NothingToLookUp(f"cluster {job.cluster_id} has no crop")
        crop = bgr_crop(roi.crop)
        phash = crop_phash(crop)
        name = self.backend.name
        hit = await self.cache.find(name, phash)
        if hit is not None:
            findings = hit.findings
            provenance = LookupProvenance(backend=name, cached=True, hash_distance=hit.distance,
                                          latency_ms=round(hit.search_ms, 2), job_id=job.id)
        else:
            start = perf_counter()
            try:
                async with asyncio.timeout(self.timeout_s):
                    findings = await self.backend.lookup(crop)
            except TimeoutError:
                raise BackendError(f"{name} gave no answer within {self.timeout_s:g} s") from None
            latency_ms = (perf_counter() - start) * 1000
            await self.cache.put(name, phash, findings, latency_ms)
            provenance = LookupProvenance(backend=name, latency_ms=round(latency_ms, 2),
                                          job_id=job.id)
        annotations = annotations_for(findings, provenance, roi, crop.shape)
        if annotations:
            await self.store.add_annotations(cluster.id, annotations, session=job.session)
        return {"backend": name, "cached": provenance.cached,
                "hash_distance": provenance.hash_distance, "latency_ms": provenance.latency_ms,
                "phash": f"{phash:016x}", "findings": len(findings),
                "annotations": len(annotations)}
