"""The perceptual-hash lookup cache shared by all workers and robots (thesis 5.4.5).

A crop whose 64-bit pHash lies within PMEM_LOOKUP_CACHE_RADIUS bits of a crop looked up before
reuses that answer instead of calling the service again. The default radius, 10, comes from
real images (bench/enrichment.py, `radius`): on the crops of the RoboSherlock samples, the same
object re-cut a pixel off, scaled or JPEG re-encoded stays within 10 bits in 99-100 % of cases
(87 % when shifted 2 px), while different objects never came closer than 22 bits and 0.005 %
of pairs of random non-overlapping windows of the same frames did.

`lookup_cache` in MongoDB holds the answers, one document per service and hash: {_id,
service, hash (the 64 bits as a signed int64), findings, latency_ms, created}. The search
for the nearest hash runs in memory: every worker keeps the hashes of each service in a numpy
array, loads them at start and follows new ones through a change stream. XOR and popcount over
1 M hashes (8 MB) take about 1.2 ms (p95 < 2 ms, bench/enrichment.py), for any radius.
Multi-index hashing would index the hash in chunks and use the pigeonhole principle; with 1 M
hashes the chunks must be about log2(1 M) = 20 bits for the buckets to be small, so 3 chunks,
and radius 10 then needs every chunk searched within radius 3: 3 x 1,562 chunk keys and, for
uniform hashes, ~2,300 candidates to fetch and check per lookup (more for real ones, which
cluster). Scanning the array is simpler and faster at this size.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from dataclasses import dataclass
from time import perf_counter

import numpy as np
from pymongo.errors import DuplicateKeyError, PyMongoError

from percept_memory.ingest.backends import Finding
from percept_memory.ingest.jobs import utc_now

log = logging.getLogger(__name__)
INITIAL_CAPACITY = 1024


def to_int64(value: int) -> int:
    """64 unsigned bits as the signed int64 BSON stores."""
    return value - (1 << 64) if value >= 1 << 63 else value


class HashIndex:
    """64-bit hashes in a growing numpy array; nearest neighbour by Hamming distance."""

    def __init__(self) -> None:
        self._hashes = np.empty(INITIAL_CAPACITY, np.uint64)
        self.size = 0

    def add(self, hashes: list[int] | np.ndarray) -> None:
        values = np.asarray(hashes, dtype=np.int64).view(np.uint64)
        needed = self.size + len(values)
        if needed > len(self._hashes):
            grown = np.empty(max(needed, 2 * len(self._hashes)), np.uint64)
            grown[: self.size] = self._hashes[: self.size]
            self._hashes = grown
        self._hashes[self.size : needed] = values
        self.size = needed

    def nearest(self, value: int, radius: int) -> tuple[int, int] | None:
        """(hash as signed int64, distance) of the closest hash within `radius`, or None."""
        if not self.size:
            return None
        query = np.array([to_int64(value)], np.int64).view(np.uint64)[0]
        distances = np.bitwise_count(self._hashes[: self.size] ^ query)
        best = int(distances.argmin())
        if distances[best] > radius:
            return None
        return int(self._hashes[best : best + 1].view(np.int64)[0]), int(distances[best])


@dataclass
class CacheHit:
    findings: list[Finding]
    distance: int
    search_ms: float


class LookupCache:
    """The shared cache on the `lookup_cache` collection (an AsyncMongoClient collection).
    Use as `async with LookupCache(collection, radius) as cache:`."""

    def __init__(self, collection, radius: int):
        self.collection = collection
        self.radius = radius
        self._indexes: dict[str, HashIndex] = {}
        self._follower: asyncio.Task | None = None
        self._added_here: set[tuple[str, int]] = set()  # by put(), until the stream shows them

    async def __aenter__(self) -> LookupCache:
        """Follow new entries (change stream opened first, so none is missed), then load the
        stored ones. An entry seen both ways is in the index twice, which is harmless."""
        stream = await self.collection.watch([{"$match": {"operationType": "insert"}}])
        self._follower = asyncio.create_task(self._follow(stream))
        cursor = self.collection.find({}, {"_id": 0, "service": 1, "hash": 1})
        batch: dict[str, list[int]] = {}
        async for doc in cursor:
            batch.setdefault(doc["service"], []).append(doc["hash"])
        for service, hashes in batch.items():
            self.index(service).add(hashes)
        return self

    async def __aexit__(self, *exc) -> None:
        if self._follower is not None:
            self._follower.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._follower

    def index(self, service: str) -> HashIndex:
        return self._indexes.setdefault(service, HashIndex())

    async def _follow(self, stream) -> None:
        try:
            async with stream:
                async for change in stream:
                    doc = change["fullDocument"]
                    key = (doc["service"], doc["hash"])
                    if key in self._added_here:  # indexed already by put()
                        self._added_here.discard(key)
                    else:
                        self.index(doc["service"]).add([doc["hash"]])
        except PyMongoError as error:  # the cache still works; other workers' entries wait
            log.warning("lookup cache: stopped following new entries: %s", error)

    async def find(self, service: str, phash: int) -> CacheHit | None:
        """The answer stored for the nearest hash within the radius, if any."""
        start = perf_counter()
        near = self.index(service).nearest(phash, self.radius)
        if near is None:
            return None
        doc = await self.collection.find_one({"service": service, "hash": near[0]})
        if doc is None:  # removed from the collection since
            return None
        findings = [Finding.model_validate(f) for f in doc["findings"]]
        return CacheHit(findings, near[1], (perf_counter() - start) * 1000)

    async def put(self, service: str, phash: int, findings: list[Finding],
                  latency_ms: float) -> None:
        """Store an answer (the first one for a hash stays) and index it here at once."""
        key = to_int64(phash)
        try:
            result = await self.collection.update_one(
                {"service": service, "hash": key},
                {"$setOnInsert": {"findings": [f.model_dump() for f in findings],
                                  "latency_ms": round(latency_ms, 1), "created": utc_now()}},
                upsert=True,
            )
        except DuplicateKeyError:  # another worker stored this hash at the same moment
            return
        if result.upserted_id is not None:
            self._added_here.add((service, key))
            self.index(service).add([key])
