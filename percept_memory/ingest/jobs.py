"""The durable enrichment queue: the `jobs` collection (DESIGN.md: Ingest and enrichment).

The memory pipeline enqueues one lookup job per stored cluster that has a crop (`LookupEnqueuer`,
one of its stages, in the transaction that marks the stage done), so ingest never waits on a
lookup and no cluster is looked up twice.
Workers take jobs through `JobQueue`, on pymongo's AsyncMongoClient:

- claim: one find_one_and_update of the job due first sets a lease: a fresh token, the worker's
  name, `lease_until` and the session the job's writes run in. A running job's `due` is the
  end of its lease, so when its worker dies (no more heartbeats) the job falls due again and
  the next claim takes it over, first killing the dead worker's session: killed inside its
  transaction, it left the transaction open on the server, holding the cluster, its object and
  its scene (and the consolidator of that map) until the server reaped it, 90 s later;
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

import logging
import random
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from typing import Any, Literal

from bson import ObjectId
from pymongo import ReturnDocument, UpdateOne
from pymongo.errors import OperationFailure

from percept_memory.converters import name_of
from percept_memory.memory.schema import JOBS
from percept_memory.memory.store import MemoryStore
from percept_memory.memory.types import ImageROI, WebLookup

log = logging.getLogger(__name__)

LOOKUP = "lookup"
State = Literal["queued", "running", "done", "failed"]
STATES: tuple[State, ...] = ("queued", "running", "done", "failed")
MAX_BACKOFF_S = 600.0


def utc_now() -> datetime:
    return datetime.now(UTC)


# the clusters of some scenes that have a crop to look up, and no lookup's results already
# (scenes imported from a scene log of an enriched memory: looked up again, each got twice
# the results)
def _with_crop(scene_ids: Sequence[ObjectId]) -> dict:
    return {"scene_id": {"$in": list(scene_ids)}, "hypotheses": {"$elemMatch": {
        "_type": name_of(ImageROI), "crop": {"$ne": None}}},
        "annotations._type": {"$ne": name_of(WebLookup)}}


class LookupEnqueuer:
    """A stage of the memory pipeline (memory/pipeline.py): a lookup job for every cluster
    with a crop of the scenes it is given. Upserts, one per cluster (a cluster has one lookup
    job, ever: unique index), so a job is never queued twice."""

    name = "lookups"
    belief = False  # a rebuilt map needs no lookup again

    def __init__(self, store: MemoryStore):
        self.store = store
        self.jobs = store.db[JOBS]

    def apply(self, scene_ids: Sequence[ObjectId], map_name: str, session) -> None:
        at = utc_now()
        clusters = self.store.clusters.find(_with_crop(scene_ids), {"scene_id": 1},
                                            session=session)
        upserts = [UpdateOne({"kind": LOOKUP, "cluster_id": c["_id"]}, {"$setOnInsert": {
            "scene_id": c["scene_id"], "state": "queued", "attempts": 0, "due": at,
            "created": at, "updated": at}}, upsert=True) for c in clusters]
        if upserts:
            self.jobs.bulk_write(upserts, ordered=False, session=session)

    def reset(self, map_name: str) -> None:
        """Nothing to forget: lookups are no part of a map's belief."""


@dataclass
class Job:
    """A claimed job, as its worker holds it: `lease` is the token that proves the claim."""

    id: ObjectId
    cluster_id: ObjectId
    lease: ObjectId
    attempts: int
    taken_over_from: str | None = None  # the worker whose lease had expired
    session: Any = None  # the job's writes run in it (AsyncClientSession); ended by its worker


class JobQueue:
    """The worker's side of the queue (async)."""

    def __init__(self, collection, *, lease_s: float, max_attempts: int, backoff_s: float):
        self.jobs = collection
        self.lease = timedelta(seconds=lease_s)
        self.max_attempts = max_attempts
        self.backoff_s = backoff_s

    async def claim(self, worker: str) -> Job | None:
        """The job due first, leased to `worker`, with the session its writes are to run in;
        None when nothing is due. A job whose lease expired on its last allowed attempt is
        marked failed instead of run once more."""
        while True:
            at = utc_now()
            token = ObjectId()
            session = self.jobs.database.client.start_session()
            before = None
            # a dead worker's jobs first: due at their lease's end, they sort behind every job
            # queued before it, and would wait for the whole backlog (their open writes too)
            for due, index in (({"state": "running", "due": {"$lte": at}}, "state_updated"),
                               ({"due": {"$lte": at}}, "due")):
                before = await self.jobs.find_one_and_update(
                    due,
                    {"$set": {"state": "running", "worker": worker, "lease": token,
                              "lease_until": at + self.lease, "due": at + self.lease,
                              "updated": at, "session": session.session_id},
                     "$inc": {"attempts": 1}},
                    sort=[("due", 1)], return_document=ReturnDocument.BEFORE,
                    hint=index,  # (running jobs are few: by state, not the backlog by due)
                )
                if before is not None:
                    break
            if before is None:
                await session.end_session()
                return None
            lost = before.get("worker") if before["state"] == "running" else None
            if lost and before.get("session"):
                await self._kill(before["session"])
            job = Job(before["_id"], before["cluster_id"], token, before["attempts"] + 1, lost,
                      session)
            if job.attempts <= self.max_attempts:
                return job
            await session.end_session()
            await self._finish(job, "failed", error=(
                f"gave up after {self.max_attempts} attempts: worker {lost} stopped "
                "(its lease expired)" if lost else before.get("error")))

    async def _kill(self, session_id: dict) -> None:
        """Abort what the session of a job whose lease expired left open (without the right
        to, the server's own reaping is waited out)."""
        try:
            await self.jobs.database.client.admin.command("killSessions", [session_id])
        except OperationFailure as error:
            log.warning("could not end an expired job's session (%s)", error)

    async def heartbeat(self, job: Job) -> bool:
        """Extend the lease; False when the job is no longer this worker's."""
        at = utc_now()
        result = await self.jobs.update_one(
            {"_id": job.id, "lease": job.lease},
            {"$set": {"lease_until": at + self.lease, "due": at + self.lease, "updated": at}},
        )
        return result.matched_count == 1

    async def complete(self, job: Job, outcome: dict[str, Any]) -> bool:
        """Done: an earlier attempt's error goes (a done job showing one reads as failed)."""
        return await self._finish(job, "done", outcome=outcome, error=None)

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
    with their last error: what `pmem jobs` and GET /api/jobs show. `limit` 0: the counts
    alone (MongoDB's limit 0 would be every job)."""
    jobs = store.db[JOBS]
    counts = {name: jobs.count_documents({"state": name}) for name in STATES}
    found = jobs.find({"state": state} if state else {}).sort("updated", -1).limit(limit)
    return {"counts": counts, "jobs": [job_summary(doc) for doc in found] if limit else []}


def job_summary(doc: dict) -> dict:
    """A job document as JSON: ids as hex, times as ISO 8601, no lease token or session."""
    def plain(value: Any) -> Any:
        if isinstance(value, ObjectId):
            return str(value)
        if isinstance(value, datetime):
            return value.isoformat()
        if isinstance(value, dict):
            return {key: plain(item) for key, item in value.items()}
        return value

    return {("id" if key == "_id" else key): plain(value)
            for key, value in doc.items() if key not in ("lease", "session")}


def requeue_failed(store: MemoryStore) -> int:
    """Queue every failed job again with fresh attempts (after fixing what made them fail)."""
    at = utc_now()
    result = store.db[JOBS].update_many(
        {"state": "failed"},
        {"$set": {"state": "queued", "due": at, "attempts": 0, "updated": at}},
    )
    return result.modified_count
