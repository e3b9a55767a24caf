"""The fold lease: one folder per job at a time, kept for as long as the folder lives.

A redis-py lock with a time to live of fold_lease_seconds, renewed from a thread every
third of that while the round runs (a round of a large frame outlasts a lease); a folder
that dies stops renewing and its lease lapses. The lease only spares duplicate work: a
round's writes are correct without it (each tile's transaction WATCHes its version)."""

from __future__ import annotations

import threading
from types import TracebackType

import redis
from redis.exceptions import LockError

from worker.config import config
from worker.store import keys


class FoldLease:
    def __init__(self, conn: redis.Redis, job_id: str, wait: bool) -> None:
        self.lock = conn.lock(keys.fold_lock(job_id), timeout=config().fold_lease_seconds, blocking=wait,
                              blocking_timeout=2 * config().fold_lease_seconds, thread_local=False)
        self._stop = threading.Event()
        self._renewer = threading.Thread(target=self._renew, name="fold-lease", daemon=True)

    def __enter__(self) -> bool:
        """True if this process holds the lease now."""
        if not self.lock.acquire():
            return False
        self._renewer.start()
        return True

    def _renew(self) -> None:
        while not self._stop.wait(config().fold_lease_seconds / 3):
            try:
                self.lock.extend(config().fold_lease_seconds, replace_ttl=True)
            except (LockError, redis.RedisError):
                return  # lost: another folder may take it (its writes and ours stay correct)

    def __exit__(self, kind: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None) -> None:
        if not self._renewer.is_alive() and self._renewer.ident is None:
            return  # never held
        self._stop.set()
        self._renewer.join()
        try:
            self.lock.release()
        except (LockError, redis.RedisError):
            pass
