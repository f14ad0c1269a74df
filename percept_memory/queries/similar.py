"""Find more like this: the observations that look most like a cluster, an object or an image.

The query names what to start from (a cluster, an object by id or name: its latest
observation, or an uploaded PNG/JPEG crop) and what may be found (robots, regions, maps, a
time window); the answer ranks clusters by their mean similarity over the descriptors both
sides have (each a cosine of unit vectors, memory/types/appearance.py), with each
descriptor's own. The vector search is memory/similarity.py's index, brought up to date with
MongoDB before each answer: here, or in a server by its keeper's thread (memory/index_keeper.py),
waited for at most settings.similarity_wait_s (the answer says how many stored clusters were
not indexed yet when it had to stop waiting).
"""

from __future__ import annotations

import base64
import binascii
from typing import Annotated, Any

from pydantic import BaseModel, BeforeValidator, Field, StringConstraints, model_validator

from percept_memory.converters import ConversionError
from percept_memory.converters.images import decode_file
from percept_memory.memory.errors import NotFound
from percept_memory.memory.index_keeper import IndexKeeper
from percept_memory.memory.schema import CLUSTERS
from percept_memory.memory.settings import Settings
from percept_memory.memory.similarity import RowFilter, SimilarityIndex
from percept_memory.memory.store import MemoryStore
from percept_memory.memory.types import Id
from percept_memory.memory.types.appearance import crop_descriptors, hash_bits, perceptual_hash

from .clusters import HIT_FIELDS
from .engine import QueryEngine
from .model import MAX_LIST, Name, Strict, Subject, Time, listed
from .ops import QueryError
from .results import ClusterHit

MAX_SIMILAR = 100
MAX_IMAGE_BYTES = 4 * 2**20  # an uploaded crop, before base64
MAX_IMAGE_PIXELS = 4_000_000  # read from its header before it is decoded

Names = Annotated[list[Name], BeforeValidator(listed), Field(max_length=MAX_LIST)]


class SimilarQuery(Strict):
    """What to start from (one of cluster, object, image), how many to find, and where."""

    cluster: Id | None = Field(default=None, description="a cluster (observation) id")
    object: Subject | None = Field(default=None, description=(
        "an object (its latest observation): its id, or text naming it as where-is reads it"))
    image: Annotated[str, StringConstraints(max_length=(MAX_IMAGE_BYTES + 2) // 3 * 4)] | None \
        = Field(default=None, description="a PNG or JPEG crop, base64 (JSON body only)")
    k: Annotated[int, Field(ge=1, le=MAX_SIMILAR)] = Field(default=10,
                                                           description="how many to find")
    descriptor: Names = Field(default=[], description=(
        "compare by these descriptors only (default: every one both sides have)"))
    region: Names = Field(default=[], description="region names (any of them)")
    robot: Names = Field(default=[], description="robot names (any of them)")
    map: Names = Field(default=[], description="map names (any of them)")
    after: Time | None = Field(default=None, description="at or after this time")
    before: Time | None = Field(default=None, description="at or before this time")

    @model_validator(mode="after")
    def _one_start(self):
        given = [name for name in ("cluster", "object", "image") if getattr(self, name)]
        if len(given) != 1:
            raise ValueError("give one of cluster, object or image to start from"
                             + (f", not {' and '.join(given)}" if given else ""))
        if None not in (self.after, self.before) and self.after > self.before:
            raise ValueError("`after` is later than `before`")
        return self


class SimilarHit(ClusterHit):
    similarity: float  # the mean over `descriptors`, 0..1
    descriptors: dict[str, float]  # per descriptor both have: cosine, 0..1


class SimilarPage(BaseModel):
    start: str  # the cluster compared with (the object's latest), or "image"
    descriptors: list[str]  # those of the start the search used
    items: list[SimilarHit]
    not_indexed_yet: int = Field(default=0, description=(
        "stored clusters the search could not look at: the server's index had not described "
        "them yet when the wait for it ended (it waits for a burst of ingest to pause, then "
        "catches up; 0: it searched them all)"))


class Similarity:
    """similar_to on a store, with its index in the settings' data directory, caught up by
    each query, or `in_background` by a keeper's thread (a server's: close() ends it)."""

    def __init__(self, store: MemoryStore, settings: Settings | None = None,
                 index: SimilarityIndex | None = None, in_background: bool = False):
        settings = settings or Settings()
        self.store = store
        self.index = index or SimilarityIndex.of(store, settings)
        self.keeper = IndexKeeper(self.index, settings.similarity_niceness) \
            if in_background else None
        self.wait_s = settings.similarity_wait_s

    def close(self) -> None:
        if self.keeper is not None:
            self.keeper.stop()

    def similar_to(self, query: SimilarQuery | None = None, **fields: Any) -> SimilarPage:
        """The k clusters that look most like the start, best first."""
        query = query or SimilarQuery.model_validate(fields)
        if self.keeper is None:
            self.index.refresh()
            not_indexed = 0
        else:
            not_indexed = self.keeper.current(self.wait_s)
        start, vectors = self._start(query)
        if query.descriptor:
            unknown = sorted(set(query.descriptor) - set(self.index.names()))
            if unknown:
                raise QueryError(f"no descriptor {', '.join(unknown)}: one of "
                                 f"{', '.join(self.index.names()) or '(none indexed yet)'}")
            vectors = {n: v for n, v in vectors.items() if n in query.descriptor}
        if not vectors:
            raise QueryError(f"{start} has no descriptor to compare by (a crop, a perceptual "
                             "hash, a colour histogram or a feature vector)")
        where = RowFilter(robot=query.robot, region=query.region, map=query.map,
                          after=query.after, before=query.before)
        exclude = [query.cluster or start] if start != "image" else []
        matches = self.index.search(vectors, query.k, where, exclude)
        docs = {d["_id"]: d for d in self.store.db[CLUSTERS].find(
            {"_id": {"$in": [m.cluster_id for m in matches]}}, HIT_FIELDS)}
        items = [SimilarHit.of(docs[m.cluster_id], similarity=m.similarity,
                               descriptors=m.descriptors)
                 for m in matches if m.cluster_id in docs]
        return SimilarPage(start=str(start), descriptors=sorted(vectors), items=items,
                           not_indexed_yet=not_indexed)

    def _start(self, query: SimilarQuery) -> tuple[Any, dict]:
        if query.image is not None:
            return "image", image_descriptors(query.image)
        cluster_id = query.cluster
        if query.object is not None:
            seen = QueryEngine(self.store).last_seen(query.object, limit=1)
            if not seen:
                raise NotFound("object", query.object)
            cluster_id = seen[0].cluster_id
        if self.index.holds(cluster_id):
            return cluster_id, self.index.descriptors_of(cluster_id)
        # not indexed (yet: the keeper may still be catching up), or not stored
        described = self.index.described([cluster_id])
        if not described:
            raise NotFound("cluster", cluster_id)
        return cluster_id, described[0].vectors()


def image_descriptors(encoded: str) -> dict:
    """The descriptors of an uploaded crop, as ImageROI gives a stored one's; its size is
    checked in the file's header before it is decoded."""
    try:
        data = base64.b64decode(encoded, validate=True)
    except (binascii.Error, ValueError):
        raise QueryError("image: not base64") from None
    if len(data) > MAX_IMAGE_BYTES:
        raise QueryError(f"image: {len(data)} bytes, over the limit of {MAX_IMAGE_BYTES}")
    try:
        pixels = decode_file(data, "bgr8", MAX_IMAGE_PIXELS)
    except ConversionError as error:
        raise QueryError(f"image: the file {error}") from None
    if pixels.ndim not in (2, 3) or min(pixels.shape[:2]) < 8:
        raise QueryError("image: too small to compare (at least 8 x 8 pixels)")
    found = crop_descriptors(pixels)
    found["phash"] = hash_bits(perceptual_hash(pixels))
    return found
