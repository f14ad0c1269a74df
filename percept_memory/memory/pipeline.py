"""The memory pipeline: the after-store stages of every stored scene, run from an outbox exactly
once, in time order per map (DESIGN.md: the memory pipeline and maps).

A scene is written together with its outbox entry, in one transaction (store.py), so an
acknowledged scene is never without its pending stages. Consolidators (`Pipeline`: a thread of
the server, `pmem consolidate`, or a caller waiting for the belief) take each map's entries
strictly in (time, scene id) order and apply every stage (identity consolidation, enqueueing
lookups, ...) to a batch of scenes in one transaction that also removes the batch's entries:
each stage's writes land exactly once or not at all, whoever dies when.

- One writer per map: a lease in `maps` (owner, token, until, session), taken when free or
  expired and checked in every stage transaction (a fence: a consolidator that lost its lease,
  paused longer than the lease, cannot commit). Any number of maps go in parallel, in any
  process. A consolidator killed inside a transaction leaves it open on the server, holding
  the map's document for the server's transaction lifetime (a minute by default, then reaped:
  90 s measured); so the lease names the session its transactions run in, and whoever takes
  an expired lease over kills that session first, aborting what it left open.
- Failures are retried with exponential backoff while the map waits, so its order holds.
  After `max_attempts` a scene is *held*: kept with its error and shown (`pmem pipeline`,
  GET /api/pipeline, the /pipeline page), and the scenes behind it go on: one bad scene never
  stops a robot's memory. A held scene is retried by hand (`pmem pipeline --retry`).
- Ingest first: a consolidator thread shares the interpreter with the server it runs in, so it
  gives way to scenes being stored there (`ingesting`, around a whole request: reading,
  parsing, storing): it waits while a batch is being stored and until ingest has been quiet
  for QUIET_S (a client's turn between two requests is shorter), at most YIELD_S, and takes
  at most BUSY_BATCH scenes at a time until ingest has paused for BUSY_S. Everything is still
  consolidated, in order, exactly once; a burst of ingest is just not slowed by it (a robot
  that posts a scene every 100 ms leaves it the gaps), and it catches up after the burst. A
  caller that waits for the belief (`wait`) ends the pause for quiet: it wants its scene
  consolidated now, and is woken by the commit rather than by its next poll. The thread
  works on the maps its process stored scenes of as they come, and looks for every map with
  work (stored elsewhere, to rebuild, due for a retry) every `poll_s`.
- Durable where it must be: a scene and its outbox entry commit as the client's write concern
  says (majority: journaled). What the stages write is derived from them, and the leases are
  advisory (the fence decides): a stage transaction and a lease commit without waiting for
  the journal (UNJOURNALED: each wait cost a scene waited for ~1.3 ms). A crash may lose the last
  ~100 ms of them; their outbox entries come back with them, so those scenes are consolidated
  again, still exactly once, and whoever kept the lost belief in memory finds its version
  gone and reads it again.
- Late scenes: a scene older than the newest consolidated scene of its map (it arrived late,
  or was held and retried) rebuilds the map: the belief stages forget the map and every scene
  of the map is queued for them again. So the belief always equals what consolidating the
  map's scenes in time order gives, and `pmem reconsolidate` is the same code: it asks every
  map to be rebuilt.
"""

from __future__ import annotations

import logging
import os
import socket
import threading
import time
from collections.abc import Iterable, Iterator, Sequence
from contextlib import contextmanager
from datetime import UTC, datetime, timedelta
from itertools import islice
from typing import Protocol

from bson import ObjectId
from pymongo import ASCENDING, ReturnDocument, WriteConcern
from pymongo.errors import (
    BulkWriteError,
    ConfigurationError,
    ConnectionFailure,
    DuplicateKeyError,
    OperationFailure,
    PyMongoError,
)

from .documents import outbox_entry
from .schema import MAPS, OUTBOX, SCENES
from .store import MemoryStore
from .types import iso_from_timestamp

log = logging.getLogger(__name__)

LEASE_S = 30.0
BATCH = 32
MAX_ATTEMPTS = 5
BACKOFF_S = 0.5  # then 1, 2, 4 s: a failing scene holds its map about 8 s before it is held
POLL_S = 0.25
WAIT_POLL_S = 0.05  # a caller waiting for scenes another process consolidates asks this often
RECENT = 4096  # scenes committed here that a waiter in this process is told of
YIELD_S = 1.0  # the longest a consolidator thread waits for ingest to pause
QUIET_S = 0.02  # ingest has paused when nothing was stored this long
BUSY_S = 1.0  # after ingest, a consolidator thread takes at most BUSY_BATCH at a time this long
# Scenes a transaction while ingest is busy: a transaction's round trips are most of a scene
# waited for, so one at a time fell behind a robot posting 20 kitchen scenes/s (bench/pipeline.py
# --rate 20: lag p95 11.2 s after 600 scenes); four keep up (0.62 s), 10/s is as before (0.1 s)
BUSY_BATCH = 4
ORDER = [("time", ASCENDING), ("_id", ASCENDING)]
# the stages' transactions and the leases: acknowledged when applied, journaled within the
# server's commit interval (100 ms by default), not waited for (see the docstring)
UNJOURNALED = WriteConcern(w=1, j=False)
DUPLICATE_KEY = 11000


class Stage(Protocol):
    """An after-store stage: what happens to every stored scene, once."""

    name: str
    belief: bool  # part of a map's belief: run again on every scene when the map is rebuilt

    def apply(self, scene_ids: Sequence[ObjectId], map_name: str, session) -> None:
        """Do the stage's work for these scenes of one map, in this order, in the session's
        transaction."""

    def reset(self, map_name: str) -> None:
        """Forget what the stage knows of a map (belief stages), before it is rebuilt."""


class LeaseLost(Exception):
    """Another consolidator took the map over (this one was paused past its lease)."""


def utc_now() -> datetime:
    return datetime.now(UTC)


class Pipeline:
    """Runs the stages on the outbox's scenes, map by map, under a lease per map."""

    def __init__(self, store: MemoryStore, stages: Sequence[Stage], *, lease_s: float = LEASE_S,
                 batch: int = BATCH, max_attempts: int = MAX_ATTEMPTS,
                 backoff_s: float = BACKOFF_S, poll_s: float = POLL_S):
        self.store = store
        self.stages = list(stages)
        self.outbox = store.db[OUTBOX]
        self.maps = store.db[MAPS]
        self.leases = self.maps.with_options(write_concern=UNJOURNALED)
        self.lease = timedelta(seconds=lease_s)
        self.batch = batch
        self.max_attempts = max_attempts
        self.backoff_s = backoff_s
        self.poll_s = poll_s
        self.owner = f"{socket.gethostname()}:{os.getpid()}:{ObjectId()}"
        self._wake = threading.Event()
        self._woken: set[str] = set()  # maps this process stored scenes of, not yet worked on
        self._scanned_at = -poll_s  # when run_forever last looked for every map with work
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._ingest = threading.Condition()
        self._storing = 0  # batches being stored in this process now
        self._stored_at = -BUSY_S  # when the last one was (time.monotonic)
        self._waiting = 0  # callers of `wait` in this process now
        # the scenes this pipeline's last batches committed, with their maps (newest last, at
        # most RECENT), for whoever waits for them here: told by the commit instead of asking
        # the database; and the maps it is rebuilding that are not back where they were
        self._went_through: dict[ObjectId, str] = {}
        self._catching_up: dict[str, tuple] = {}
        self._commits = threading.Condition()
        self._forever = threading.local()  # .running: in the thread of run_forever

    # --- running ---------------------------------------------------------------------------

    def run_once(self) -> int:
        """One pass over every map with work: returns the scenes that went through."""
        maps = set(self.outbox.distinct("map", {"held": False}))
        maps |= {doc["_id"] for doc in self.maps.find({"rebuild": True}, {"_id": 1})}
        return self._run_on(maps)

    def _run_on(self, maps: Iterable[str]) -> int:
        """One pass over these maps: returns the scenes that went through."""
        return sum(self._work_on(name) for name in sorted(maps))

    def drain(self, timeout: float | None = None, progress=None) -> int:
        """Run until no scene is pending (also those a consolidator elsewhere is working on),
        or the timeout passes: returns the scenes that went through here."""
        deadline = None if timeout is None else time.monotonic() + timeout
        total = 0
        while (deadline is None or time.monotonic() < deadline) and self.pending():
            done = self.run_once()
            total += done
            if progress and done:
                progress(done)
            if not done:
                time.sleep(self.poll_s / 5)
        return total

    def pending(self) -> int:
        """Scenes waiting for their stages, held ones aside; maps waiting to be rebuilt count
        as pending too."""
        return (self.outbox.count_documents({"held": False})
                + self.maps.count_documents({"rebuild": True}))

    def _maps_pending(self, scene_ids: Sequence[ObjectId]) -> list[str]:
        """The maps of those of these scenes still waiting for their stages."""
        return sorted(self.outbox.distinct("map", {"_id": {"$in": list(scene_ids)},
                                                   "held": False}))

    def held(self, scene_ids: Sequence[ObjectId]) -> bool:
        """Whether a scene of these scenes' maps is held (its stage kept failing, here or in
        another process): their belief misses it until it is retried, whatever went through
        after it. One look at the outbox's few held entries (the maps of scenes this process
        committed are known without asking)."""
        with self._commits:
            maps = {self._went_through[i] for i in scene_ids if i in self._went_through}
        if unknown := [i for i in scene_ids if i not in self._went_through]:
            maps |= set(self.store.db[SCENES].distinct("map", {"_id": {"$in": unknown}}))
        return self.outbox.find_one({"map": {"$in": sorted(maps)}, "held": True},
                                    {"_id": 1}) is not None

    def _maps_catching_up(self, scene_ids: Sequence[ObjectId]) -> list[str]:
        """The maps of these scenes being rebuilt, not back yet where they were before."""
        rebuilding = self.maps.distinct("_id", {"catch_up": {"$ne": None}})
        if not rebuilding:  # (the usual case: one look at a few documents)
            return []
        return sorted(self.store.db[SCENES].distinct("map", {"_id": {"$in": list(scene_ids)},
                                                             "map": {"$in": rebuilding}}))

    def wait(self, scene_ids: Sequence[ObjectId], timeout: float) -> bool:
        """Until these scenes went through and their maps' belief is current (True) or the
        timeout passed (False): a late scene makes its map rebuild, and goes through first,
        while the scenes after it are still to go through again. A scene of their maps held
        keeps it from being current (False at once). Works on them here unless a background
        thread of this pipeline does."""
        deadline = time.monotonic() + timeout
        with self._ingest:  # someone waits for the belief: no pause for ingest to go quiet
            self._waiting += 1
            self._ingest.notify_all()
        self._wake.set()
        try:
            while True:
                if self._thread is not None and self._committed(scene_ids, deadline):
                    # (told by this process's thread: no need to ask the database)
                    return (self._caught_up(scene_ids, deadline - time.monotonic())
                            and not self.held(scene_ids))
                maps = self._maps_pending(scene_ids) or self._maps_catching_up(scene_ids)
                if not maps:
                    return not self.held(scene_ids)
                if time.monotonic() >= deadline:
                    return False
                if self._thread is None:
                    if not sum(self._work_on(name) for name in maps):
                        # another consolidator works on them: asked again after WAIT_POLL_S
                        self._committed(scene_ids, deadline)
                    elif self._went_through_all(scene_ids) and self._caught_up(scene_ids, 0):
                        return not self.held(scene_ids)
        finally:
            with self._ingest:
                self._waiting -= 1

    def _committed(self, scene_ids: Sequence[ObjectId], deadline: float) -> bool:
        """Whether this process's thread committed these scenes within WAIT_POLL_S (at most
        until the deadline)."""
        with self._commits:
            return self._commits.wait_for(lambda: self._went_through_all(scene_ids),
                                          min(WAIT_POLL_S, max(deadline - time.monotonic(), 0)))

    def _caught_up(self, scene_ids: Sequence[ObjectId], timeout: float) -> bool:
        """Whether the maps of these scenes, committed here, are not being rebuilt by this
        process's pipeline, or are back where they were, within `timeout` seconds."""
        with self._commits:
            maps = {self._went_through[i] for i in scene_ids if i in self._went_through}
            return self._commits.wait_for(lambda: not maps & self._catching_up.keys(),
                                          max(timeout, 0))

    def _went_through_all(self, scene_ids: Sequence[ObjectId]) -> bool:
        """Whether this process committed all these scenes' stages (recently)."""
        with self._commits:
            return all(i in self._went_through for i in scene_ids)

    def start(self) -> Pipeline:
        """Run in a background thread until stop()."""
        self._stop.clear()
        self._thread = threading.Thread(target=self.run_forever, name="pmem-pipeline",
                                        daemon=True)
        self._thread.start()
        return self

    def stop_soon(self) -> None:
        """Ask run_forever to return after what it is doing (from a signal handler too)."""
        self._stop.set()
        self._wake.set()

    def _stopping(self) -> bool:
        """Whether run_forever, in this thread, was asked to stop: it stops between batches,
        the rest waiting in the outbox (durable), not after the whole backlog (a SIGTERM
        waited for it past docker's grace period). A caller's own wait or drain goes on."""
        return self._stop.is_set() and getattr(self._forever, "running", False)

    def stop(self) -> None:
        """Stop the background thread, after the batch it is doing."""
        self.stop_soon()
        if self._thread is not None:
            self._thread.join()
            self._thread = None

    def wake(self, maps: Iterable[str] = ()) -> None:
        """New scenes were stored (of these maps, when the caller knows): look now, not at the
        next poll."""
        with self._commits:
            self._woken.update(maps)
        self._wake.set()

    def arriving(self) -> None:
        """Scenes are arriving (a part of a request's body came): the pipeline's thread gives
        way as just after a batch was stored. A stalled client stops counting at once, as it
        sends nothing (a body read inside `ingesting` held it back for as long: one robot
        sending a byte a second slowed every map's consolidation 50 times)."""
        with self._ingest:
            self._stored_at = time.monotonic()

    @contextmanager
    def ingesting(self) -> Iterator[None]:
        """Around storing a batch of scenes in this process (or a whole request that brings
        one): the pipeline's thread gives way meanwhile (see `_give_way`)."""
        with self._ingest:
            self._storing += 1
        try:
            yield
        finally:
            with self._ingest:
                self._storing -= 1
                self._stored_at = time.monotonic()
                self._ingest.notify_all()

    def _give_way(self) -> int:
        """How many scenes to take next: in the pipeline's own thread, wait while a batch is
        being stored in this process (at most YIELD_S), then BUSY_BATCH while ingest is busy,
        else a whole batch."""
        if threading.current_thread() is not self._thread:
            return self.batch
        deadline = time.monotonic() + YIELD_S
        with self._ingest:
            while (pause := self._until_quiet()) > 0 and (left := deadline - time.monotonic()) > 0:
                self._ingest.wait(min(pause, left))
            busy = self._storing or time.monotonic() - self._stored_at < BUSY_S
        return min(BUSY_BATCH, self.batch) if busy else self.batch

    def _until_quiet(self) -> float:
        """Seconds until ingest in this process will have been quiet for QUIET_S (inf while a
        batch is being stored)."""
        if self._storing:
            return float("inf")
        if self._waiting:
            return 0.0
        return QUIET_S - (time.monotonic() - self._stored_at)

    def run_forever(self) -> None:
        """Work whenever there is work, until stop(); a database outage is waited out. A pass
        takes what was due when it looked: after one that did work, the next looks after
        QUIET_S (at once when this process stores a scene), not while whoever waited for that
        work reads its answer. A pass that fails is logged and tried again."""
        self._forever.running = True
        while not self._stop.is_set():
            try:
                done = self._pass()
            except PyMongoError as error:
                log.warning("pipeline: the database is not answering (%s); retrying", error)
                done = 0
                self._stop.wait(5 * self.poll_s)
            except Exception:  # a bug outside any scene's stages: said, and kept trying (a
                # thread that ended would leave the server storing scenes no one consolidates)
                log.exception("pipeline: a pass failed; retrying")
                done = 0
                self._stop.wait(5 * self.poll_s)
            self._wake.wait(QUIET_S if done else self.poll_s)
            self._wake.clear()

    def _pass(self) -> int:
        """run_forever's pass: over every map with work once `poll_s` has passed since the
        last such look (scenes stored elsewhere, rebuilds asked for, retries due), else over
        the maps this process stored scenes of since: a scene waited for costs no search for
        the maps with work."""
        with self._commits:
            woken, self._woken = self._woken, set()
        if time.monotonic() - self._scanned_at < self.poll_s:
            return self._run_on(woken)
        self._scanned_at = time.monotonic()
        return self.run_once()  # (the maps woken for have work: they are among those found)

    # --- one map ---------------------------------------------------------------------------

    def _work_on(self, map_name: str) -> int:
        with self.store.client.start_session() as session:  # the lease's transactions
            lease = self._acquire(map_name, session)
            if lease is None:
                return 0
            token = lease["lease"]["token"]
            catch_up = _watermark(lease.get("catch_up"))
            self._catch_up(map_name, catch_up)  # (another consolidator may have begun it)
            released = False
            try:
                if lease.get("rebuild"):
                    catch_up = self._rebuild(map_name, token, _later(
                        lease.get("consolidated"), catch_up))
                    lease["consolidated"] = None
                count, released = self._consolidate(map_name, token, lease.get("consolidated"),
                                                    catch_up, session)
                return count
            except LeaseLost:
                log.warning("pipeline: lost the lease of map %r to another consolidator",
                            map_name)
                return 0
            finally:
                if not released:
                    self.leases.update_one({"_id": map_name, "lease.token": token},
                                           {"$set": {"lease": None}})

    def _consolidate(self, map_name: str, token: ObjectId, watermark, catch_up: tuple | None,
                     session) -> tuple[int, bool]:
        """The map's due entries in order, a batch per transaction; a batch that fails is
        tried scene by scene, so only the failing scene waits and is counted against. The
        scenes that went through, and whether the lease went with the last batch: a batch that
        leaves no entry due releases it in its own transaction (no round trip of its own).
        `catch_up`: where a rebuild of the map must get back to (its belief is not current
        until then)."""
        count, size = 0, self.batch
        while not self._stopping():
            wanted = min(size, self._give_way())
            entries = self._next(map_name, wanted + 1)
            if not entries:
                if catch_up and not self.outbox.find_one({"map": map_name, "held": False},
                                                         {"_id": 1}):
                    # (what it was to get back to went away: held, or deleted)
                    self._caught_up_with(map_name, token)
                return count, False
            last = len(entries) <= wanted
            entries = entries[:wanted]
            head = (entries[0]["time"], entries[0]["_id"])
            if watermark is not None and head <= tuple(watermark):
                log.info("pipeline: a late scene rebuilds map %r", map_name)
                catch_up = self._rebuild(map_name, token, _later(watermark, catch_up))
                watermark = None
                continue
            back = catch_up is not None and (entries[-1]["time"], entries[-1]["_id"]) >= catch_up
            try:
                self._apply(map_name, token, entries, session, release=last, caught_up=back)
            # not the scene's fault: try again later (a mongod restarting answers as a
            # deployment without sessions until it is a replica set's member again)
            except (LeaseLost, ConnectionFailure, ConfigurationError):
                raise
            except Exception as error:  # any stage's failure: kept with the scene, retried
                if len(entries) > 1:
                    size = 1
                    continue
                self._failed(entries[0], error)
                if entries[0]["attempts"] + 1 < self.max_attempts:
                    return count, False  # the map waits out the backoff, in order
                continue
            count += len(entries)
            if back:
                catch_up = None
            if last:
                return count, True
            size = self.batch
            watermark = (entries[-1]["time"], entries[-1]["_id"])
        return count, False

    def _next(self, map_name: str, size: int) -> list[dict]:
        """The next entries of the map that are due, in order (none while the first waits)."""
        now = utc_now()
        entries = []
        for entry in self.outbox.find({"map": map_name, "held": False}).sort(ORDER).limit(size):
            if entry["due"] is not None and entry["due"] > now:
                break
            entries.append(entry)
        return entries

    def _apply(self, map_name: str, token: ObjectId, entries: list[dict], session,
               release: bool = False, caught_up: bool = False) -> None:
        """The stages on these entries and their removal, in one transaction that checks the
        lease is still ours (and ends it, when `release`; and says a rebuild is back where it
        was, when `caught_up`)."""
        ids = [entry["_id"] for entry in entries]
        last = entries[-1]

        def work(session):
            ending = {"lease": None} if release else {"lease.until": utc_now() + self.lease}
            if caught_up:
                ending["catch_up"] = None
            fenced = self.maps.update_one(
                {"_id": map_name, "lease.token": token},
                {"$set": {**ending, "consolidated": [last["time"], last["_id"]],
                          "updated": utc_now()}},
                session=session)
            if not fenced.matched_count:
                raise LeaseLost(map_name)
            for stage in self.stages:
                todo = [entry["_id"] for entry in entries if stage.name not in entry["done"]]
                if todo:
                    try:
                        stage.apply(todo, map_name, session)
                    except PyMongoError:
                        raise
                    except Exception as error:
                        raise StageFailed(stage.name, error) from error
            self.outbox.delete_many({"_id": {"$in": ids}}, session=session)

        self.store._transaction(work, session=session, write_concern=UNJOURNALED)
        with self._commits:
            self._went_through.update(dict.fromkeys(ids, map_name))
            for old in list(islice(self._went_through, max(len(self._went_through) - RECENT, 0))):
                del self._went_through[old]
            if caught_up:
                self._catching_up.pop(map_name, None)
            self._commits.notify_all()  # (the waiters of these scenes and of catching up)

    def _failed(self, entry: dict, error: Exception) -> None:
        attempts = entry["attempts"] + 1
        held = attempts >= self.max_attempts
        message = str(error) if isinstance(error, StageFailed) else repr(error)
        due = None if held else utc_now() + timedelta(seconds=self.backoff_s * 2 ** (attempts - 1))
        self.outbox.update_one({"_id": entry["_id"]}, {"$set": {
            "attempts": attempts, "held": held, "due": due, "error": message[:2000],
            "failed_at": utc_now()}})
        log.warning("pipeline: scene %s of map %r failed (attempt %d%s): %s", entry["_id"],
                    entry["map"], attempts, ", held" if held else "", message)

    # --- leases and rebuilds ---------------------------------------------------------------

    def _acquire(self, map_name: str, session) -> dict | None:
        """The map's document with a fresh lease of ours, its transactions to run in
        `session`; None when another holds it. The session of an expired lease is killed
        first (a read is not held up by what a transaction left open; the write would be)."""
        now = utc_now()
        ours = {"$set": {"lease": {"owner": self.owner, "token": ObjectId(),
                                   "until": now + self.lease, "session": session.session_id}}}
        try:  # a free lease (the usual case: one round trip): no transaction of it is open
            return self.leases.find_one_and_update({"_id": map_name, "lease": None}, ours,
                                                   upsert=True,
                                                   return_document=ReturnDocument.AFTER)
        except DuplicateKeyError:  # held, maybe expired
            pass
        expired = self.maps.find_one({"_id": map_name, "lease.until": {"$lt": now}},
                                     {"lease.session": 1})
        if expired is None:
            return None
        if expired["lease"].get("session"):
            self._kill(expired["lease"]["session"])
        return self.leases.find_one_and_update({"_id": map_name, "lease.until": {"$lt": now}},
                                               ours, return_document=ReturnDocument.AFTER)

    def _kill(self, session_id: dict) -> None:
        """Abort whatever the session of a lease that ran out left open (its consolidator
        died or lost the lease): without the right to, the server's own reaping is waited
        out."""
        try:
            self.store.client.admin.command("killSessions", [session_id])
        except OperationFailure as error:
            log.warning("pipeline: could not end an expired lease's session (%s)", error)

    def _rebuild(self, map_name: str, token: ObjectId, until) -> tuple | None:
        """Forget the map's belief and queue every scene of the map for the belief stages
        again. Idempotent: a consolidator that dies halfway leaves the request for the next.
        `until`: where the belief was (a waiter is told it is current once it is back there),
        kept with the map as `catch_up` and returned."""
        until = _watermark(until)
        self.maps.update_one({"_id": map_name, "lease.token": token},
                             {"$set": {"rebuild": True, "consolidated": None,
                                       "catch_up": list(until) if until else None}})
        self._catch_up(map_name, until)
        belief = [stage.name for stage in self.stages if stage.belief]
        others = [stage.name for stage in self.stages if not stage.belief]
        for stage in self.stages:
            if stage.belief:
                stage.reset(map_name)
        self.outbox.update_many({"map": map_name}, {"$pullAll": {"done": belief}})
        scenes = self.store.db[SCENES].find({"map": map_name}, {"timestamp": 1}).sort(
            [("map", ASCENDING), ("timestamp", ASCENDING), ("_id", ASCENDING)])
        for chunk in _chunks(scenes, 1000):
            entries = [outbox_entry(doc["_id"], map_name, doc["timestamp"], others)
                       for doc in chunk]
            try:
                self.outbox.insert_many(entries, ordered=False)
            except BulkWriteError as error:  # those in the outbox already keep their entry
                if any(e["code"] != DUPLICATE_KEY for e in error.details["writeErrors"]):
                    raise
        if not self.maps.update_one({"_id": map_name, "lease.token": token},
                                    {"$set": {"rebuild": False}}).matched_count:
            raise LeaseLost(map_name)
        return until

    def _catch_up(self, map_name: str, until: tuple | None) -> None:
        """Note in this process where the map's rebuild is to get back to (None: nowhere)."""
        with self._commits:
            if until:
                self._catching_up[map_name] = until
            elif self._catching_up.pop(map_name, None):
                self._commits.notify_all()

    def _caught_up_with(self, map_name: str, token: ObjectId) -> None:
        """A rebuild with nothing left to do is back where it can get."""
        self.maps.update_one({"_id": map_name, "lease.token": token},
                             {"$set": {"catch_up": None}})
        self._catch_up(map_name, None)


def _watermark(value) -> tuple | None:
    """A map's point in its scenes' order, (time, scene id), as stored ([time, id]) or None."""
    return tuple(value) if value else None


def _later(a, b) -> tuple | None:
    """The later of two points (either may be None)."""
    points = [p for p in (_watermark(a), _watermark(b)) if p]
    return max(points) if points else None


class StageFailed(Exception):
    """A stage raised: the message names the stage."""

    def __init__(self, stage: str, error: Exception):
        super().__init__(f"{stage}: {type(error).__name__}: {error}")


def _chunks(items: Iterable, size: int):
    chunk = []
    for item in items:
        chunk.append(item)
        if len(chunk) == size:
            yield chunk
            chunk = []
    if chunk:
        yield chunk


# --- what the pipeline is doing, for the CLI, the API and the UI -------------------------------


def request_rebuild(store: MemoryStore, maps: Iterable[str] | None = None) -> list[str]:
    """Ask for these maps' belief (default: every map) to be rebuilt from their scenes by the
    consolidators (`pmem reconsolidate`). Scenes stored before maps existed get theirs."""
    from .types.scene import default_map

    scenes = store.db[SCENES]
    for doc in scenes.find({"map": {"$exists": False}}, {"robot": 1, "frame": 1}):
        scenes.update_one({"_id": doc["_id"]}, {"$set": {
            "map": default_map(doc.get("robot", ""), doc.get("frame", "map"))}})
    names = sorted(maps) if maps is not None else sorted(scenes.distinct("map"))
    for name in names:
        store.db[MAPS].update_one({"_id": name}, {"$set": {"rebuild": True}}, upsert=True)
    return names


def retry_held(store: MemoryStore) -> int:
    """Queue the held scenes again (they are late now: their maps will be rebuilt)."""
    return store.db[OUTBOX].update_many({"held": True}, {"$set": {
        "held": False, "attempts": 0, "due": None}}).modified_count


# a map whose belief is being rebuilt: asked for, or under way until it is back where it was
REBUILDING = {"$or": [{"rebuild": True}, {"catch_up": {"$ne": None}}]}


def rebuilding(db, map_name: str | None = None) -> list[str]:
    """The maps of the database whose belief is being rebuilt (of this one, if named): their
    answers hold the scenes consolidated so far."""
    named = {} if map_name is None else {"_id": map_name}
    return sorted(db[MAPS].distinct("_id", {**named, **REBUILDING}))


def status(store: MemoryStore, held_limit: int = 50) -> dict:
    """How far the belief of each map is: the newest consolidated scene's time, the scenes
    pending and held, whether it is being rebuilt and who holds its lease (one that ran out
    is no one's); the held scenes with their errors."""
    outbox = store.db[OUTBOX]
    counts: dict[str, dict[str, int]] = {}
    for row in outbox.aggregate([{"$group": {"_id": {"map": "$map", "held": "$held"},
                                             "n": {"$sum": 1}}}]):
        kind = "held" if row["_id"]["held"] else "pending"
        counts.setdefault(row["_id"]["map"], {})[kind] = row["n"]
    maps = {doc["_id"]: doc for doc in store.db[MAPS].find()}
    rows, now = [], utc_now()
    for name in sorted(set(maps) | set(counts)):
        doc = maps.get(name, {})
        lease = doc.get("lease") or {}
        if lease and lease["until"] < now:  # its holder died without letting it go: no one
            lease = {}
        watermark = doc.get("consolidated")
        rows.append({
            "map": name,
            "consolidated_until": iso_from_timestamp(watermark[0]) if watermark else None,
            "consolidated_until_ns": watermark[0] if watermark else None,
            "pending": counts.get(name, {}).get("pending", 0),
            "held": counts.get(name, {}).get("held", 0),
            # asked for, or under way until it is back where the belief was
            "rebuilding": bool(doc.get("rebuild") or doc.get("catch_up")),
            "consolidator": lease.get("owner"),
        })
    held = [{"scene_id": str(e["_id"]), "map": e["map"], "time": iso_from_timestamp(e["time"]),
             "time_ns": e["time"], "attempts": e["attempts"], "error": e["error"]}
            for e in outbox.find({"held": True}).sort(ORDER).limit(held_limit)]
    return {"maps": rows, "held": held}
