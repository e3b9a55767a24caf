"""The reducer: `photonfarm reducer`, the process that folds jobs, publishes their images,
keeps them fed and ends them. Any number may run; the API holds no job state.

Each active job is owned by one reducer at a time under its reducer lease (a redis-py lock,
keys.reducer, lease_seconds long, renewed every third of that): the owner keeps the job's
state in its memory between checkpoints (worker/store/overlay.py), so one owner folds each
job's rounds. A reducer that dies stops renewing; within a lease another one takes the job
and rebuilds the state from the tiles (a lost overlay costs work, never a pass: the
exact-once protocol is on the tiles, worker/store/state.py). A round also takes the fold
lease (worker/store/fold_lease.py), which a worker's stale fold and a job's end respect.

One reducer at a time, under the reaper lease (keys.REAPER), re-issues lost batches and
settles jobs with nothing left in flight (worker/scheduler.py `reap`).

A fold round, `fold`, is these steps (each opened by a comment naming it):
lease, read deltas, merge, estimate (TiledState.fold_round), publish the image and the
estimate (worker/store/published.py: what every API process serves), write the batches'
inputs, checkpoint, decide the end.
"""

from __future__ import annotations

import logging
import os
import signal
import socket
import threading
import time
from dataclasses import replace

import redis
from redis.exceptions import LockError
from redis.lock import Lock

from worker.config import config
from worker.logs import configure_logging
from worker.scheduler import reap
from worker.store import Jobs, keys, policy
from worker.store.connection import connect
from worker.store.fold_lease import FoldLease
from worker.store.overlay import OVERLAYS
from worker.store.policy import Status
from worker.store.published import Published
from worker.store.state import FoldContended, Folded, LostDeltas, UnreadableDelta

log = logging.getLogger("photonfarm.reducer")
REAP_SECONDS = 2.0
PRUNE_SECONDS = 60.0


def fold(jobs: Jobs, job_id: str, wait: bool = False, decide: bool = True, checkpoint: bool = False) -> Folded | None:
    """One fold round of the job's accepted batches, if any is new to this process
    (`checkpoint`: a checkpoint round in any case), by whoever gets the fold lease (`wait`:
    wait for it). With `decide`, a job whose error reached its threshold converges. None
    if there was nothing to fold or another folder had the lease.
    A batch whose delta this process cannot read is never folded: the job fails, and a
    checkpoint round folds the readable batches into its final image."""
    try:
        return fold_round(jobs, job_id, wait, decide, checkpoint)
    except UnreadableDelta as exc:
        jobs.r.hdel(keys.tofold(job_id), exc.batch_id)
        jobs.fail(job_id, f"cannot fold {exc}")
        fold_round(jobs, job_id, wait=True, decide=False, checkpoint=True)
        return None


def fold_round(jobs: Jobs, job_id: str, wait: bool, decide: bool, checkpoint: bool) -> Folded | None:
    """`fold`'s round, step by step; raises UnreadableDelta (the round wrote nothing)."""
    if not jobs.r.hlen(keys.tofold(job_id)):
        return None
    # Lease: one folder per round (the reducer that owns the job, or a worker's stale fold).
    with FoldLease(jobs.r, job_id, wait) as held:
        if not held:
            return None
        record = jobs.get(job_id)
        accepted = jobs.foldable(job_id)
        read_at = time.time()  # batches accepted after it wait for the next round
        if record is None or not record.setup or not accepted:
            return None
        checkpoint = checkpoint or record.stopping or record.status in policy.FINAL  # no later round
        fresh = accepted.keys() - OVERLAYS.batches(job_id)
        if not fresh and not checkpoint:
            return None  # all in this process's image already (a due checkpoint waits for news or the end)
        if not checkpoint:  # paced: the batches that came together, over the rounds before the next
            fresh, accepted = jobs.paced(record, fresh, accepted)
        fold_start = time.perf_counter()
        tiling = jobs.tiling(record)
        # Read deltas, merge, estimate: the state (this process's overlay, or the tiles'),
        # each tile's pending deltas of the fresh batches added, the error estimated.
        try:
            folded, tiles = jobs.tiles.fold_round(job_id, tiling, record.integrator, record.folded_emitted,
                                                  record.folded_passes, record.counters, accepted, checkpoint)
        except FoldContended:
            return None  # another folder holds the tiles now; its round counts
        except LostDeltas as exc:  # a state node restarted: render them again, the next round folds the rest
            jobs.refill(job_id, exc.batch_ids)
            return None
        # Publish the image and the estimate: the API serves them; then the round's record
        # (its length, the passes the image holds) and the error history.
        rounds = (*record.fold_rounds, policy.Round(len(fresh), time.perf_counter() - fold_start, folded.rebuilt)
                  )[-config().rounds_kept:]
        if fresh or folded.rebuilt:
            jobs.images.publish(job_id, Published.of(record.integrator, folded.state, folded.estimate))
        jobs.tiles.publish(job_id, folded, {
            "passes": folded.state.passes, "photons": folded.state.emitted,
            "seconds": round(record.elapsed_seconds(), 3), "error": folded.error}, rounds, read_at)
        # Write the batches' inputs: what the next batches read. A regular round's writes
        # end when the next round is due (policy.checkpoint_seconds), one as long as the
        # rounds so far predict for as many batches as this one took.
        next_seconds = policy.round_seconds(rounds, max(1, len(fresh))) or rounds[-1].seconds
        until = None if checkpoint else time.time() + policy.checkpoint_seconds(next_seconds)
        try:
            folded = replace(folded, stages=folded.stages | jobs.tiles.write_inputs(job_id, tiling,
                                                                                    record.integrator))
        except FoldContended:
            tiles = []  # the overlay is dropped: another folder holds the tiles now, and its round counts
        # Checkpoint: the tiles that are due (the long part of a big frame's round), and the
        # record counts the batches every tile has now written. A forced checkpoint (a
        # worker's: it serves no image; the job's last) writes every tile and keeps no overlay.
        if tiles:
            cpu = time.process_time()
            try:
                with OVERLAYS.writing(job_id):  # a failed write drops the overlay
                    written, complete = jobs.tiles.checkpoint(job_id, tiling, record.integrator, tiles,
                                                              keep=not checkpoint, until=until)
                    if complete:
                        jobs.tiles.settle(job_id, complete)
                    if checkpoint:
                        OVERLAYS.drop(job_id)
                    else:
                        OVERLAYS.put(job_id, written)
            except FoldContended:
                return folded  # another folder holds the tiles now; its round counts
            folded = replace(folded, checkpointed=not written.batches,
                             stages=folded.stages | {"write state": time.process_time() - cpu})
        jobs.note_cost(job_id, time.perf_counter() - fold_start)
    # Decide the end: a job whose error reached its threshold converges.
    status = jobs.status(job_id)
    if status in policy.FINAL:
        jobs.expire_tiles(job_id)  # a fold racing the final move rewrote tiles
    elif decide and status == Status.RUNNING and policy.converged(record.settings, folded.error):
        jobs.converge(job_id)
    return folded


def fold_owned(jobs: Jobs, owned: list[str]) -> int:
    """A fold round for every owned job with accepted batches waiting whose round is due,
    and at once the final round of a job an accepted batch ended. Returns how many were
    folded. A round that fails other than by Redis is logged and the other jobs fold on
    (its batches stay accepted; the next round tries again)."""
    folded = 0
    for job_id in owned:
        try:
            folded += jobs.end_if_decided(job_id) or jobs.fold_if_due(job_id) is not None
        except redis.RedisError:
            raise
        except Exception:  # one job's failing round must not stop the others'
            log.exception("fold round failed", extra={"job": job_id})
    return folded


def next_look_in(jobs: Jobs, owned: list[str]) -> float:
    """How long the reducer waits (for news) before its next look: until the first round of
    an owned job is due, so that a paced round starts when due rather than up to a look
    later; at most fold_poll_seconds (a batch accepted meanwhile may make a round due, or
    a job may come to this reducer) and at least fold_wait_min_seconds (a due round another
    process holds the fold lease for is not polled for in a spin)."""
    due = [d for job_id in owned if (d := jobs.next_round_in(job_id)) is not None]
    return max(config().fold_wait_min_seconds, min([config().fold_poll_seconds, *due]))


def hold(lock: Lock) -> bool:
    """Keep the lease if this process holds it (its time renewed), else try to take it; True
    while this process holds it."""
    if lock.local.token is not None:
        try:
            lock.extend(config().fold_lease_seconds, replace_ttl=True)
            return True
        except LockError:
            pass  # lapsed: another process may hold it now
    return bool(lock.acquire(blocking=False))


class Reducer:
    """The reducer's three threads: the leases (take and renew), the folder, the reaper."""

    def __init__(self, jobs: Jobs) -> None:
        self.jobs = jobs
        self.name = f"{socket.gethostname()}:{os.getpid()}"
        self._leases: dict[str, Lock] = {}  # owned jobs' reducer leases
        self._owned: list[str] = []
        self._lock = threading.Lock()
        self._reaper = self._lease(keys.REAPER)
        self._stop = threading.Event()
        self._threads = [threading.Thread(target=target, name=name, daemon=True) for name, target in
                         (("leases", self._keep_leases), ("folder", self._fold), ("reaper", self._reap))]

    def _lease(self, key: str) -> Lock:
        return self.jobs.r.lock(key, timeout=config().fold_lease_seconds, thread_local=False)

    def owned(self) -> list[str]:
        with self._lock:
            return list(self._owned)

    def claim(self) -> list[str]:
        """Renew the leases of the jobs this reducer owns, take those of active jobs no other
        reducer holds, and forget jobs it lost or that ended (their overlays dropped: a job
        that comes back is rebuilt from the tiles). Returns the jobs owned."""
        active = set(self.jobs.active_ids())
        for job_id in sorted(active - self._leases.keys()):
            self._leases[job_id] = self._lease(keys.reducer(job_id))
        for job_id in list(self._leases):
            lease = self._leases[job_id]
            if job_id in active and hold(lease):
                continue
            if job_id not in active and lease.local.token is not None:
                release(lease)
            del self._leases[job_id]
        owned = sorted(self._leases)
        with self._lock:
            if set(owned) != set(self._owned):
                log.info("jobs owned", extra={"reducer": self.name, "jobs": owned})
            self._owned = owned
        OVERLAYS.keep_only(set(owned))
        return owned

    def _keep_leases(self) -> None:
        while not self._stop.is_set():
            try:
                self.claim()
            except redis.RedisError as exc:
                log.warning("reducer: redis unavailable: %s", exc)
            self._stop.wait(config().fold_lease_seconds / 3)

    def _fold(self) -> None:
        while not self._stop.is_set():
            try:
                owned = self.owned()
                self.jobs.wait_for_news(next_look_in(self.jobs, owned))
                fold_owned(self.jobs, self.owned())
            except redis.RedisError as exc:
                log.warning("folder: redis unavailable: %s", exc)
                self._stop.wait(config().fold_poll_seconds)
            except Exception:  # the thread lives on: the next round may succeed
                log.exception("folder: a pass over the jobs failed")
                self._stop.wait(config().fold_poll_seconds)

    def _reap(self) -> None:
        last_prune = 0.0
        while not self._stop.wait(REAP_SECONDS):
            try:
                if not hold(self._reaper):
                    continue  # another reducer reaps
                if n := reap(self.jobs):
                    log.info("re-issued lost batches", extra={"reissued": n})
                if time.monotonic() - last_prune > PRUNE_SECONDS:
                    self.jobs.prune()  # ids of jobs past their retention
                    last_prune = time.monotonic()
            except redis.RedisError as exc:
                log.warning("reaper: redis unavailable: %s", exc)
            except Exception:  # the thread lives on: the next look may succeed
                log.exception("reaper: a look failed")

    def start(self) -> Reducer:
        for thread in self._threads:
            thread.start()
        return self

    def stop(self) -> None:
        """Stop the threads and give up the leases: another reducer takes the jobs at once."""
        self._stop.set()
        for thread in self._threads:
            if thread.ident is not None:  # started
                thread.join()
        for lease in [*self._leases.values(), self._reaper]:
            if lease.local.token is not None:
                release(lease)


def release(lease: Lock) -> None:
    try:
        lease.release()
    except (LockError, redis.RedisError):
        pass  # lapsed, or Redis gone: it lapses by itself


def run(redis_url: str) -> int:
    """`photonfarm reducer`: reduce until SIGTERM or SIGINT, then give the jobs up."""
    configure_logging()
    stopping = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stopping.set())
    reducer = Reducer(Jobs(connect(redis_url))).start()
    log.info("reducer started", extra={"reducer": reducer.name})
    while not stopping.wait(1.0):
        pass
    reducer.stop()
    log.info("reducer stopped", extra={"reducer": reducer.name})
    return 0
