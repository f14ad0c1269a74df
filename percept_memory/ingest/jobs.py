"""The durable enrichment queue: the `jobs` collection (DESIGN.md: Ingest and enrichment).

Ingest enqueues one lookup job per new cluster that has a crop (`LookupEnqueuer`, an after-store
stage of the ingest service: one insert_many per batch, so ingest never waits on a lookup).
Workers take jobs through `JobQueue`, on pymongo's AsyncMongoClient:

- claim: one find_one_and_update of the job due first sets a lease: a fresh token, the worker's
  name and `lease_until`. A running job's `due` is the end of its lease, so when its worker dies
  (no more heartbeats) the job falls due again and the next claim takes it over;
- heartbeat, complete, retry, fail, release: only with the current token, so a worker that lost
  its lease can never overwrite the one that took the job over;
- a failure is retried after an exponential backoff (backoff x 2^(attempt-1), +-20 % jitter,
  at most 10 minutes) until `max_attempts` claims, then the job is `failed`, keeping the error
  (`pmem jobs`, GET /api/jobs); a permanent failure (the service rejected the crop, the
  cluster is gone) fails at once;
- on graceful shutdown a worker releases its unfinished jobs: queued again, attempt not counted.

A job document: {_id, kind, cluster_id, scene_id, state (queued | running | done | failed),
attempts, due (claimable from then on; unset once done or failed), lease, lease_until, worker,
created, updated, error (the last one), outcome}. Clocks: leases compare the workers' clocks,
which NTP keeps within milliseconds of each other; the lease is seconds long.
"""

from __future__ import annotations

import random
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from typing import Any, Literal

from bson import ObjectId
from pymongo import ReturnDocument
from pymongo.errors import BulkWriteError

from percept_memory.memory.schema import JOBS
from percept_memory.memory.store import MemoryStore
from percept_memory.memory.types import ImageROI, Scene

LOOKUP = "lookup"
State = Literal["queued", "running", "done", "failed"]
STATES: tuple[State, ...] = ("queued", "running", "done", "failed")
MAX_BACKOFF_S = 600.0
DUPLICATE_KEY = 11000


def utc_now() -> datetime:
    return datetime.now(UTC)


def lookup_jobs(scenes: Sequence[Scene], at: datetime) -> list[dict]:
    """The job documents for the stored scenes' clusters that have a crop to look up."""
    return [
        {"kind": LOOKUP, "cluster_id": cluster.id, "scene_id": scene.id, "state": "queued",
         "attempts": 0, "due": at, "created": at, "updated": at}
        for scene in scenes for cluster in scene.clusters
        if (roi := cluster.hypothesis_of(ImageROI)) is not None and roi.crop is not None
    ]


class LookupEnqueuer:
    """After-store stage of the ingest service: a lookup job for every new cluster with a crop,
    in one insert_many per batch. A cluster has one lookup job, ever (unique index), so
    enqueueing again is harmless."""

    def __init__(self, store: MemoryStore):
        self.jobs = store.db[JOBS]

    def __call__(self, scenes: Sequence[Scene]) -> None:
        jobs = lookup_jobs(scenes, utc_now())
        if not jobs:
            return
        try:
            self.jobs.insert_many(jobs, ordered=False)
        except BulkWriteError as error:
            if any(e["code"] != DUPLICATE_KEY for e in error.details["writeErrors"]):
                raise


@dataclass
class Job:
    """A claimed job, as its worker holds it: `lease` is the token that proves the claim."""

    id: ObjectId
    cluster_id: ObjectId
    lease: ObjectId
    attempts: int
    taken_over_from: str | None = None  # the worker whose lease had expired


class JobQueue:
    """The worker's side of the queue (async)."""

    def __init__(self, collection, *, lease_s: float, max_attempts: int, backoff_s: float):
        self.jobs = collection
        self.lease = timedelta(seconds=lease_s)
        self.max_attempts = max_attempts
        self.backoff_s = backoff_s

    async def claim(self, worker: str) -> Job | None:
        """The job due first, leased to `worker`; None when nothing is due. A job whose lease
        expired on its last allowed attempt is marked failed instead of run once more."""
        while True:
            at = utc_now()
            token = ObjectId()
            before = await self.jobs.find_one_and_update(
                {"due": {"$lte": at}},
                {"$set": {"state": "running", "worker": worker, "lease": token,
                          "lease_until": at + self.lease, "due": at + self.lease,
                          "updated": at},
                 "$inc": {"attempts": 1}},
                sort=[("due", 1)], return_document=ReturnDocument.BEFORE,
            )
            if before is None:
                return None
            lost = before.get("worker") if before["state"] == "running" else None
            job = Job(before["_id"], before["cluster_id"], token, before["attempts"] + 1, lost)
            if job.attempts <= self.max_attempts:
                return job
            await self._finish(job, "failed", error=(
                f"gave up after {self.max_attempts} attempts: worker {lost} stopped "
                "(its lease expired)" if lost else before.get("error")))

    async def heartbeat(self, job: Job) -> bool:
        """Extend the lease; False when the job is no longer this worker's."""
        at = utc_now()
        result = await self.jobs.update_one(
            {"_id": job.id, "lease": job.lease},
            {"$set": {"lease_until": at + self.lease, "due": at + self.lease, "updated": at}},
        )
        return result.matched_count == 1

    async def complete(self, job: Job, outcome: dict[str, Any]) -> bool:
        return await self._finish(job, "done", outcome=outcome)

    async def retry_or_fail(self, job: Job, error: str, *, permanent: bool = False) -> State:
        """Queue the job again after its backoff, or mark it failed when it was the last
        attempt (or the error is permanent). Returns the state the job is left in."""
        if permanent or job.attempts >= self.max_attempts:
            await self._finish(job, "failed", error=error)
            return "failed"
        at = utc_now()
        delay = min(MAX_BACKOFF_S, self.backoff_s * 2 ** (job.attempts - 1))
        delay *= random.uniform(0.8, 1.2)
        await self.jobs.update_one(
            {"_id": job.id, "lease": job.lease},
            {"$set": {"state": "queued", "due": at + timedelta(seconds=delay), "error": error,
                      "updated": at},
             "$unset": {"lease": "", "lease_until": ""}},
        )
        return "queued"

    async def release(self, job: Job) -> None:
        """Give an unfinished job back (graceful shutdown): due now, attempt not counted."""
        at = utc_now()
        await self.jobs.update_one(
            {"_id": job.id, "lease": job.lease},
            {"$set": {"state": "queued", "due": at, "updated": at},
             "$unset": {"lease": "", "lease_until": ""}, "$inc": {"attempts": -1}},
        )

    async def _finish(self, job: Job, state: State, **fields: Any) -> bool:
        result = await self.jobs.update_one(
            {"_id": job.id, "lease": job.lease},
            {"$set": {"state": state, "updated": utc_now(), **fields},
             "$unset": {"due": "", "lease": "", "lease_until": ""}},
        )
        return result.matched_count == 1


# --- what the CLI and the HTTP API show (sync) ------------------------------------------------


def job_report(store: MemoryStore, state: State | None = None, limit: int = 20) -> dict:
    """Jobs per state, and the `limit` most recently updated jobs (of `state`, if given),
    with their last error: what `pmem jobs` and GET /api/jobs show."""
    jobs = store.db[JOBS]
    counts = {name: jobs.count_documents({"state": name}) for name in STATES}
    found = jobs.find({"state": state} if state else {}).sort("updated", -1).limit(limit)
    return {"counts": counts, "jobs": [job_summary(doc) for doc in found]}


def job_summary(doc: dict) -> dict:
    """A job document as JSON: ids as hex, times as ISO 8601, no lease token."""
    def plain(value: Any) -> Any:
        if isinstance(value, ObjectId):
            return str(value)
        if isinstance(value, datetime):
            return value.isoformat()
        if isinstance(value, dict):
            return {key: plain(item) for key, item in value.items()}
        return value

    return {("id" if key == "_id" else key): plain(value)
            for key, value in doc.items() if key != "lease"}


def requeue_failed(store: MemoryStore) -> int:
    """Queue every failed job again with fresh attempts (after fixing what made them fail)."""
    at = utc_now()
    result = store.db[JOBS].update_many(
        {"state": "failed"},
        {"$set": {"state": "queued", "due": at, "attempts": 0, "updated": at}},
    )
    return result.modified_count
