"""`pmem worker`: asyncio workers running lookup jobs (DESIGN.md: Ingest and enrichment).

A worker process serves one backend with at most PMEM_LOOKUP_CONCURRENCY jobs in flight (the
thesis ran one request thread per cluster; a slow service is bounded here instead). It claims a
job only when a slot is free, so a busy worker never hoards jobs and any number of processes, on
any number of machines, share the queue through the leases (jobs.py). A running job sends a
heartbeat every third of the lease; if the lease turns out lost (the worker stalled and another
took the job over) the job is cancelled here. A failure is retried with backoff, a permanent one
fails the job at once; the job keeps the error.

SIGTERM or SIGINT: claim nothing more, let the running jobs finish for up to `grace_s`, then
release the rest to the queue (their attempt not counted) and exit.
"""

from __future__ import annotations

import asyncio
import logging
import os
import signal
import socket
import subprocess
import sys
from collections import Counter
from collections.abc import Iterator
from contextlib import contextmanager

from percept_memory.ingest.backends import BackendError, RejectedLookup, open_backend
from percept_memory.ingest.jobs import Job, JobQueue
from percept_memory.ingest.lookup_cache import LookupCache
from percept_memory.ingest.lookups import Lookup, NothingToLookUp
from percept_memory.memory.async_store import AsyncMemoryStore
from percept_memory.memory.errors import NotFound
from percept_memory.memory.schema import JOBS, LOOKUP_CACHE
from percept_memory.memory.settings import Settings

log = logging.getLogger(__name__)
POLL_S = 0.5  # how often an idle worker looks for due jobs
GRACE_S = 30.0
PERMANENT = (RejectedLookup, NothingToLookUp, NotFound)


def worker_name() -> str:
    return f"{socket.gethostname()}:{os.getpid()}"


class Worker:
    """Claims jobs and runs them, `concurrency` at a time, until told to stop."""

    def __init__(self, queue: JobQueue, lookup: Lookup, *, concurrency: int,
                 name: str | None = None, poll_s: float = POLL_S):
        self.queue = queue
        self.lookup = lookup
        self.concurrency = concurrency
        self.name = name or worker_name()
        self.poll_s = poll_s
        self.heartbeat_s = queue.lease.total_seconds() / 3
        self.counts: Counter[str] = Counter()  # done, cached, retried, failed, lost, released

    async def run(self, stop: asyncio.Event, grace_s: float = GRACE_S) -> Counter[str]:
        running: set[asyncio.Task] = set()
        stopping = asyncio.create_task(stop.wait())
        try:
            while not stop.is_set():
                if len(running) >= self.concurrency:
                    await asyncio.wait({*running, stopping}, return_when=asyncio.FIRST_COMPLETED)
                    continue
                job = await self.queue.claim(self.name)
                if job is None:
                    await asyncio.wait({stopping}, timeout=self.poll_s)
                    continue
                task = asyncio.create_task(self._execute(job))
                running.add(task)
                task.add_done_callback(running.discard)
        finally:
            stopping.cancel()
            if running:
                log.info("worker %s: stopping, %d job(s) still running", self.name, len(running))
                await asyncio.wait(running, timeout=grace_s)
                for task in running:
                    task.cancel()
                await asyncio.gather(*running, return_exceptions=True)
        return self.counts

    async def _execute(self, job: Job) -> None:
        try:
            await self._run(job)
        finally:
            await job.session.end_session()

    async def _run(self, job: Job) -> None:
        if job.taken_over_from:
            log.info("job %s: taken over from %s", job.id, job.taken_over_from)
        work = asyncio.create_task(self.lookup.run(job))
        try:
            while not (await asyncio.wait({work}, timeout=self.heartbeat_s))[0]:
                if not await self.queue.heartbeat(job):
                    work.cancel()
                    self.counts["lost"] += 1
                    log.warning("job %s: lease lost, another worker has it", job.id)
                    return
            outcome = work.result()
        except asyncio.CancelledError:  # shutting down: give the job back
            work.cancel()
            await self.queue.release(job)
            self.counts["released"] += 1
            raise
        except Exception as error:  # any failure is the job's to record and retry
            await self._failed(job, error)
            return
        await self.queue.complete(job, outcome)
        self.counts["done"] += 1
        self.counts["cached"] += outcome["cached"]

    async def _failed(self, job: Job, error: Exception) -> None:
        permanent = isinstance(error, PERMANENT)
        message = str(error) if isinstance(error, (BackendError, *PERMANENT)) else (
            f"{type(error).__name__}: {error}")
        if not isinstance(error, (BackendError, *PERMANENT)):
            log.exception("job %s: unexpected error", job.id, exc_info=error)
        state = await self.queue.retry_or_fail(job, message, permanent=permanent)
        self.counts["failed" if state == "failed" else "retried"] += 1
        log.info("job %s: attempt %d failed (%s): %s", job.id, job.attempts, state, message)


async def run_worker(settings: Settings, *, backend: str | None = None,
                     concurrency: int | None = None, stop: asyncio.Event | None = None,
                     grace_s: float = GRACE_S) -> Counter[str]:
    """A worker on the store the settings name, until `stop` is set (or, when no event is
    given, until SIGTERM or SIGINT)."""
    if stop is None:
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        for signum in (signal.SIGTERM, signal.SIGINT):
            loop.add_signal_handler(signum, stop.set)
    lookups = open_backend(settings, backend)
    store = await AsyncMemoryStore.open(settings)
    try:
        async with LookupCache(store.db[LOOKUP_CACHE], settings.lookup_cache_radius) as cache:
            queue = JobQueue(store.db[JOBS], lease_s=settings.job_lease_s,
                             max_attempts=settings.job_max_attempts,
                             backoff_s=settings.job_backoff_s)
            lookup = Lookup(store, cache, lookups, settings.lookup_timeout_s)
            worker = Worker(queue, lookup, concurrency=concurrency or settings.lookup_concurrency)
            log.info("worker %s: %s backend, %d in flight", worker.name, lookups.name,
                     worker.concurrency)
            return await worker.run(stop, grace_s)
    finally:
        await lookups.aclose()
        await store.close()


@contextmanager
def worker_processes(count: int, backend: str | None = None,
                     env: dict[str, str] | None = None) -> Iterator[list[subprocess.Popen]]:
    """`count` `pmem worker` processes while the block runs (the demo, the benchmark), stopped
    with SIGTERM on the way out, so they finish or release their jobs."""
    command = [sys.executable, "-m", "percept_memory", "worker"]
    if backend:
        command += ["--backend", backend]
    processes = [subprocess.Popen(command, env=env, stdout=subprocess.DEVNULL)
                 for _ in range(count)]
    try:
        yield processes
    finally:
        for process in processes:
            process.terminate()
        for process in processes:
            try:
                process.wait(GRACE_S + 10)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()
