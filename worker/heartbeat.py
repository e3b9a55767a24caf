"""A worker process's heartbeat: a thread that, every lease_seconds / 3, says the process
is alive and extends the lease of the batch it is rendering.

Beating from a thread, not between passes, lets a single pass take longer than a lease
(a 4M-photon pass at the largest frames does), while a killed or stopped process (SIGKILL,
SIGSTOP) beats no more: its leases lapse and the reaper re-issues its batch.

While Redis is out of reach the thread beats on, and says so once when the outage starts,
again at most every OUTAGE_LOG_SECONDS, and once when Redis answers again: not at every
beat, which would flood the log.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager

import redis

from worker.config import config
from worker.store import Batch, Leases

log = logging.getLogger("photonfarm.worker")
_current: Heartbeat | None = None  # this process's heartbeat, if it runs one
OUTAGE_LOG_SECONDS = 60.0  # while Redis stays away, a warning at most this often


class Heartbeat:
    def __init__(self, leases: Leases, worker: str, interval: float | None = None) -> None:
        self.leases = leases
        self.worker = worker
        self.interval = config().lease_seconds / 3 if interval is None else interval
        self.batch: Batch | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="heartbeat", daemon=True)

    def _run(self) -> None:
        down_since = warned = 0.0  # when Redis went away (0: it answers), and when that was last said
        while True:
            try:
                self.leases.keep_alive(self.worker, self.batch)
                if down_since:
                    log.info("heartbeat: redis reachable again after %.0f s", time.monotonic() - down_since)
                    down_since = 0.0
            except redis.RedisError as exc:  # Redis restarting: beat again next time
                now = time.monotonic()
                if not down_since:
                    down_since = warned = now
                    log.warning("heartbeat: redis unavailable: %s", exc)
                elif now - warned >= OUTAGE_LOG_SECONDS:
                    warned = now
                    log.warning("heartbeat: redis unavailable for %.0f s: %s", now - down_since, exc)
            if self._stop.wait(self.interval):
                return

    def start(self) -> Heartbeat:
        global _current
        _current = self
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()


@contextmanager
def holding(batch: Batch) -> Iterator[None]:
    """Keep `batch`'s lease alive from this process's heartbeat while the block runs."""
    beat = _current
    if beat is not None:
        beat.batch = batch
    try:
        yield
    finally:
        if beat is not None:
            beat.batch = None
