"""Keeps a server's similarity index current in a thread of its own at a lower CPU priority, so
that describing the clusters a robot stores gives way to the storing itself.

Describing a cluster (its crop decoded, ORB, gradients, colour; its vectors put in the graphs)
costs more CPU than storing it: bench/similarity.py catches up ~450-650 clusters a second where
~1,100-1,400 are stored. On two cores, done at the same priority beside a robot storing scenes,
it slowed the storing by 11-20 %; at niceness 10 by ~10 % (the share of a core that niceness
still gets); at 19 not measurably (README). The price is freshness during a burst of ingest: a
query waits at most a second for the keeper (`current`), then searches what is indexed and says
how many stored clusters it could not look at yet. When the cores are not saturated the keeper
has the idle CPU and a query finds the index current; when other work at normal priority keeps
them busy for long, niceness 19 leaves it ~1.5 % of a core (PMEM_SIMILARITY_NICENESS trades
that back). Linux gives each thread its own niceness; elsewhere the keeper runs at the process's.

Niceness alone still let a keeper that described clusters on the core storing left idle slow
the storing by ~7-10 % (their shared caches, mongod's reads for it; README). So, as the memory
pipeline gives way to ingest (pipeline.py), the keeper waits while clusters are stored in bulk
(BURST of them at least BURST_PER_S a second since its last look: an import, a backlog posted at
once; a robot streaming scenes stays far below), at most MAX_DEFER_S at a time, so that a bulk
load that never pauses is still described every MAX_DEFER_S. A robot's stream is described as
it comes.
"""

from __future__ import annotations

import logging
import os
import sys
import threading
import time

from pymongo.errors import InvalidOperation

from .similarity import SimilarityIndex

log = logging.getLogger(__name__)

POLL_S = 1.0  # unasked, the keeper looks for new clusters this often (two small reads)
JOIN_S = 10.0  # stop() waits this long for a catch-up under way (a thread of a daemon after)
# Storing in bulk: this many clusters since the keeper's last look, at this rate or faster (the
# keeper describes ~450-950 a second; a robot posting 10 scenes of 6 clusters a second stores 60)
BURST = 50
BURST_PER_S = 300.0
PROBE_S = 0.1  # the keeper's first look at the rate lasts this long (within a search's wait)
MAX_DEFER_S = 10.0  # the longest the keeper waits for a bulk load to pause


class IndexKeeper:
    """A SimilarityIndex's catch-ups (`refresh`), done in a background thread started by the
    first `current` and ended by `stop`."""

    def __init__(self, index: SimilarityIndex, niceness: int, poll_s: float = POLL_S):
        self.index = index
        self.niceness = niceness
        self.poll_s = poll_s
        self.native_id: int | None = None  # the thread's, once it runs
        self._asked = 0  # catch-ups asked for by `current`
        self._done = 0  # of those, how many a finished catch-up began after
        self._changed = threading.Condition()
        self._stopping = threading.Event()
        self._thread: threading.Thread | None = None
        self._looked: tuple[int, float] | None = None  # clusters stored at its last look, when
        self._deferred_since: float | None = None  # waiting for a bulk load since

    def current(self, timeout: float) -> int:
        """Wait for a catch-up that begins after this call to finish, at most `timeout`
        seconds: returns how many stored clusters the index still lacks (0: it caught up)."""
        with self._changed:
            if self._thread is None and not self._stopping.is_set():
                self._thread = threading.Thread(target=self._run, name="pmem-similarity",
                                                daemon=True)
                self._thread.start()
            self._asked += 1
            ticket = self._asked
            self._changed.notify_all()
            if self._changed.wait_for(lambda: self._done >= ticket, timeout):
                return 0
        return self.index.behind()

    def stop(self) -> None:
        """End the thread after the catch-up under way (waiting at most JOIN_S for it), the
        index saved."""
        self._stopping.set()
        with self._changed:
            self._changed.notify_all()
            thread = self._thread
        if thread is not None:
            thread.join(JOIN_S)

    def _run(self) -> None:
        self.native_id = threading.get_native_id()
        lower_priority(self.native_id, self.niceness)
        while not self._stopping.is_set():
            with self._changed:
                ticket = self._asked
            try:
                if self._bulk_load_under_way():
                    self._stopping.wait(self.poll_s)
                    continue
                self.index.refresh()
            except InvalidOperation:  # the store was closed: nothing is left to keep current
                return
            except Exception:  # a database outage, a cluster that fails to decode: kept trying
                log.exception("similarity: the index could not catch up; retrying")
                self._stopping.wait(self.poll_s)
                continue
            with self._changed:
                self._done = ticket
                self._changed.notify_all()
                if self._asked == ticket and not self._stopping.is_set():
                    self._changed.wait(self.poll_s)  # until asked, stopped or the poll
        if self.index.unsaved:  # what was added since the last save is not described again
            self.index.save()

    def _bulk_load_under_way(self) -> bool:
        """Whether clusters are being stored in bulk (see the module's docstring) and the
        keeper has not waited MAX_DEFER_S for it yet."""
        if self._looked is None:  # the first look: the rate over a moment
            self._looked = (self.index.stored(), time.monotonic())
            self._stopping.wait(PROBE_S)
        stored, now = self.index.stored(), time.monotonic()
        looked, self._looked = self._looked, (stored, now)
        grew = stored - looked[0] >= max(BURST, BURST_PER_S * (now - looked[1]))
        if not grew:
            self._deferred_since = None
            return False
        if self._deferred_since is None:
            self._deferred_since = now
        if now - self._deferred_since < MAX_DEFER_S:
            return True
        self._deferred_since = None  # waited long enough: one catch-up, then wait again
        return False


def lower_priority(thread_id: int, niceness: int) -> None:
    """Raise the thread's niceness to at least `niceness` (on Linux, where it is the thread's
    own: elsewhere setpriority would name a process)."""
    if sys.platform == "linux":
        now = os.getpriority(os.PRIO_PROCESS, thread_id)
        os.setpriority(os.PRIO_PROCESS, thread_id, max(now, niceness))
