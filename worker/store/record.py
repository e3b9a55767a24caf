"""The job record in Redis: creation, status transitions, the job state's arrays, batch
allocation and the exactly-once merge.

A batch's seeds come from (job seed, pass index), so a re-issued batch recomputes exactly
the same passes, and the merged set makes sure they count once. The merge is one
MULTI/EXEC under WATCH of the job's version key and record: a worker that dies before EXEC
leaves nothing behind, two concurrent merges cannot both apply, and a cancel landing
between a merge's read and its write makes the merge retry and see it.

Active jobs are a set (`pf:active`) changed in the same transaction as the status: a job
is created only if the set is below the limit (checked and added atomically), and every
move to a final status removes it and gives all the job's keys their retention time.
"""

from __future__ import annotations

import json
import time
import uuid
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np
import redis

from worker.integrators import Integrator, integrator_for
from worker.integrators.base import Delta, State
from worker.settings import Settings
from worker.store import keys, policy
from worker.store.leases import Batch, Leases
from worker.store.policy import RETENTION_SECONDS, Status


COUNTER = "counter:"  # prefix of the job hash's fields that hold State.counters


class JobLimitReached(Exception):
    """The service holds as many active jobs as it allows."""


@dataclass(frozen=True)
class JobRecord:
    """A job's record (the hash `pf:job:{id}`), typed."""

    id: str
    status: Status
    settings: Settings
    scene_name: str | None
    width: int
    height: int
    created: float
    started: float | None
    finished: float | None
    passes: int  # merged
    emitted: int  # photon paths of the merged passes
    next_pass: int  # first pass index not yet allocated
    pass_seconds: float  # smoothed render seconds per pass
    render_seconds: float
    merges: int
    merge_seconds: float
    failure: str | None
    counters: dict[str, int]  # the integrator's summed scalars (Delta.counters), hash fields "counter:NAME"

    @classmethod
    def parse(cls, job_id: str, h: dict[bytes, bytes]) -> "JobRecord":
        f = {k.decode(): v.decode() for k, v in h.items()}

        def when(name: str) -> float | None:
            return float(f[name]) if f.get(name) else None

        return cls(id=job_id, status=Status(f["status"]), settings=Settings.model_validate_json(f["settings"]),
                   scene_name=f["scene_name"] or None, width=int(f["width"]), height=int(f["height"]),
                   created=float(f["created"]), started=when("started"), finished=when("finished"),
                   passes=int(f["passes"]), emitted=int(f["emitted"]), next_pass=int(f["next_pass"]),
                   pass_seconds=float(f["pass_seconds"]), render_seconds=float(f.get("render_seconds", 0.0)),
                   merges=int(f.get("merges", 0)), merge_seconds=float(f.get("merge_seconds", 0.0)),
                   failure=f.get("error") or None,
                   counters={k[len(COUNTER):]: int(v) for k, v in f.items() if k.startswith(COUNTER)})

    @property
    def n_pixels(self) -> int:
        return self.width * self.height

    @property
    def integrator(self) -> Integrator:
        return integrator_for(self.settings)

    def elapsed_seconds(self, now: float | None = None) -> float:
        if self.started is None:
            return 0.0
        end = self.finished or (time.time() if now is None else now)
        return max(0.0, end - self.started)

    @property
    def photons_per_second(self) -> float:
        elapsed = self.elapsed_seconds()
        return self.emitted / elapsed if elapsed > 0 else 0.0

    @property
    def mean_merge_seconds(self) -> float:
        return self.merge_seconds / self.merges if self.merges else 0.0


class Jobs:
    """Every read and write of job records and job states goes through here."""

    def __init__(self, conn: redis.Redis) -> None:
        self.r = conn
        self.leases = Leases(conn)

    # ------------------------------------------------------------------ records
    def create(self, scene: dict[str, Any], settings: Settings, width: int, height: int,
               scene_name: str | None, max_active: int | None = None) -> str:
        """A new queued job; raises JobLimitReached if `max_active` jobs are active."""
        job_id = uuid.uuid4().hex[:16]
        now = time.time()
        fields = {"status": Status.QUEUED.value, "scene": json.dumps(scene), "settings": settings.model_dump_json(),
                  "scene_name": scene_name or "", "width": width, "height": height, "created": now,
                  "passes": 0, "emitted": 0, "next_pass": 0, "pass_seconds": 0.0, "attempts": "{}"}
        with self.r.pipeline() as pipe:
            while True:
                try:
                    pipe.watch(keys.ACTIVE)
                    if max_active is not None and pipe.scard(keys.ACTIVE) >= max_active:
                        raise JobLimitReached(f"at most {max_active} jobs may be active at once")
                    pipe.multi()
                    pipe.hset(keys.job(job_id), mapping=fields)
                    pipe.zadd(keys.JOBS, {job_id: now})
                    pipe.sadd(keys.ACTIVE, job_id)
                    pipe.execute()
                    return job_id
                except redis.WatchError:
                    continue

    def get(self, job_id: str) -> JobRecord | None:
        h = self.r.hgetall(keys.job(job_id))
        return JobRecord.parse(job_id, h) if h else None

    def scene(self, job_id: str) -> dict[str, Any]:
        return json.loads(self.r.hget(keys.job(job_id), "scene"))

    def status(self, job_id: str) -> Status | None:
        s = self.r.hget(keys.job(job_id), "status")
        return Status(s.decode()) if s else None

    def ids(self, offset: int = 0, limit: int | None = None, newest_first: bool = False) -> list[str]:
        end = -1 if limit is None else offset + limit - 1
        ids = self.r.zrevrange(keys.JOBS, offset, end) if newest_first else self.r.zrange(keys.JOBS, offset, end)
        return [j.decode() for j in ids]

    def count(self) -> int:
        return self.r.zcard(keys.JOBS)

    def active_count(self) -> int:
        return self.r.scard(keys.ACTIVE)

    def active_ids(self) -> list[str]:
        return sorted(j.decode() for j in self.r.smembers(keys.ACTIVE))

    def _arrays_of(self, job_id: str) -> tuple[str, ...]:
        """The names of a job's state arrays (from its settings; all possible ones if unknown)."""
        settings = self.r.hget(keys.job(job_id), "settings")
        record_settings = Settings.model_validate_json(settings) if settings else Settings(error_estimation=True)
        return tuple(integrator_for(record_settings).state_widths)

    def _finish(self, pipe: redis.client.Pipeline, job_id: str, status: Status, arrays: tuple[str, ...],
                now: float) -> None:
        """Queue a move to a final status: the slot is freed and every key of the job gets
        its retention time."""
        pipe.hset(keys.job(job_id), mapping={"status": status.value, "finished": now})
        pipe.srem(keys.ACTIVE, job_id)
        for key in keys.job_keys(job_id, arrays):
            pipe.expire(key, int(RETENTION_SECONDS))

    def delete(self, job_id: str) -> None:
        """Remove a job and every key it has."""
        arrays = self._arrays_of(job_id)
        pipe = self.r.pipeline()
        pipe.delete(*keys.job_keys(job_id, arrays))
        pipe.zrem(keys.JOBS, job_id)
        pipe.srem(keys.ACTIVE, job_id)
        pipe.execute()

    def prune(self) -> int:
        """Forget ids of jobs whose records expired (retention); returns how many."""
        ids = self.ids()
        pipe = self.r.pipeline()
        for job_id in ids:
            pipe.exists(keys.job(job_id))
        gone = [job_id for job_id, exists in zip(ids, pipe.execute()) if not exists]
        if gone:
            self.r.zrem(keys.JOBS, *gone)
            self.r.srem(keys.ACTIVE, *gone)
        return len(gone)

    def history(self, job_id: str) -> list[dict[str, float]]:
        return [json.loads(x) for x in self.r.lrange(keys.history(job_id), 0, -1)]

    def last_error(self, job_id: str) -> dict[str, float] | None:
        last = self.r.lindex(keys.history(job_id), -1)
        return json.loads(last) if last else None

    # ------------------------------------------------------------------- arrays
    def _arrays(self, record: JobRecord, names: tuple[str, ...]) -> dict[str, np.ndarray]:
        integrator = record.integrator
        out = {}
        for name, blob in zip(names, self.r.mget([keys.array(record.id, name) for name in names])):
            empty = integrator.zeros(record.n_pixels, name)
            out[name] = np.frombuffer(blob, np.float64).reshape(empty.shape).copy() if blob else empty
        return out

    def has_setup(self, record: JobRecord) -> bool:
        return all(self.r.exists(keys.array(record.id, name)) for name in record.integrator.setup_arrays)

    def init_setup(self, record: JobRecord, setup: dict[str, np.ndarray]) -> None:
        """Fix the job's setup arrays (e.g. R0) once: the first writer wins."""
        for name, value in setup.items():
            self.r.set(keys.array(record.id, name), np.ascontiguousarray(value, np.float64).tobytes(), nx=True)

    def state(self, record: JobRecord) -> State | None:
        """The job state, or None before its first batch fixed the setup arrays."""
        if not self.has_setup(record):
            return None
        return record.integrator.restore(self._arrays(record, tuple(record.integrator.state_widths)),
                                         record.emitted, record.passes, record.counters)

    def batch_inputs(self, record: JobRecord) -> Any:
        """What a batch starting now needs, reading only the integrator's input arrays."""
        integrator = record.integrator
        state = integrator.restore(self._arrays(record, integrator.input_arrays), record.emitted, record.passes,
                                   record.counters)
        return integrator.batch_inputs(state)

    # ------------------------------------------------------------------ batches
    def allocate(self, job_id: str, pass_seconds: float | None = None) -> Batch | None:
        """Reserve the next range of passes, or None if the job takes no more batches."""
        key = keys.job(job_id)
        while True:
            try:
                with self.r.pipeline() as pipe:
                    pipe.watch(key)
                    record = JobRecord.parse(job_id, pipe.hgetall(key))
                    if record.status not in policy.RENDERING or policy.out_of_time(record.settings,
                                                                                   record.elapsed_seconds()):
                        return None
                    n = policy.batch_passes(pass_seconds or record.pass_seconds, record.mean_merge_seconds)
                    left = policy.passes_left(record.settings, record.next_pass)
                    n = n if left is None else min(n, left)
                    if n <= 0:
                        return None
                    batch = Batch(job_id, record.next_pass, n)
                    pipe.multi()
                    pipe.hset(key, "next_pass", batch.first + n)
                    Leases.register(pipe, batch)
                    pipe.execute()
                    return batch
            except redis.WatchError:
                continue

    def start(self, batch: Batch, worker: str) -> bool:
        """Take the lease on a batch; False if it is merged or no longer wanted. The first
        batch to start moves the job from queued to running and starts its clock."""
        if self.r.sismember(keys.merged(batch.job_id), batch.id) or not self.leases.is_inflight(batch):
            return False
        if self.status(batch.job_id) not in policy.RENDERING:  # cancelled, failed or gone meanwhile
            self.drop(batch)
            return False
        self.leases.take(batch, worker)
        self.leases.heartbeat(worker, batch.job_id, batch.id)
        self._transition(batch.job_id, frozenset({Status.QUEUED}), lambda pipe: pipe.hset(
            keys.job(batch.job_id), mapping={"status": Status.RUNNING.value, "started": time.time()}))
        return True

    def renew(self, batch: Batch, worker: str) -> Status | None:
        """After every pass: extend the lease, beat the worker's heart, and return the job's
        status (RQ's SimpleWorker sends no heartbeat during a job)."""
        pipe = self.r.pipeline()
        self.leases.renew(pipe, batch, worker)
        pipe.hget(keys.job(batch.job_id), "status")
        status = pipe.execute()[-1]
        return Status(status.decode()) if status else None

    def is_wanted(self, batch: Batch) -> bool:
        return self.status(batch.job_id) in policy.RENDERING \
            and not self.r.sismember(keys.merged(batch.job_id), batch.id) and self.leases.is_inflight(batch)

    def drop(self, batch: Batch) -> None:
        """Forget a batch that will not be merged (its job ended or was cancelled)."""
        self.leases.drop(batch)
        self.settle(batch.job_id, Status.CANCEL_REQUESTED, Status.CANCELLED)

    def record_failure(self, batch: Batch, message: str) -> bool:
        """Count a failed attempt; after MAX_ATTEMPTS the job fails. True if it failed."""
        key = keys.job(batch.job_id)
        attempts = json.loads(self.r.hget(key, "attempts") or b"{}")
        attempts[batch.id] = attempts.get(batch.id, 0) + 1
        self.r.hset(key, "attempts", json.dumps(attempts))
        if attempts[batch.id] >= policy.MAX_ATTEMPTS:
            self.fail(batch.job_id, message)
            return True
        return False

    # --------------------------------------------------------------- lifecycle
    def settle(self, job_id: str, status: Status, final: Status) -> None:
        """A job in `status` with nothing in flight ends as `final` (atomically)."""
        key = keys.job(job_id)
        arrays = self._arrays_of(job_id)
        with self.r.pipeline() as pipe:
            try:
                pipe.watch(key, keys.inflight(job_id))
                if pipe.hget(key, "status") == status.value.encode() and pipe.scard(keys.inflight(job_id)) == 0:
                    pipe.multi()
                    self._finish(pipe, job_id, final, arrays, time.time())
                    pipe.execute()
            except redis.WatchError:
                pass  # something changed meanwhile: the next merge or reap decides

    def _transition(self, job_id: str, allowed: frozenset[Status],
                    write: Callable[[redis.client.Pipeline], None]) -> bool:
        """Atomically: if the job's status is one of `allowed`, run the commands `write`
        queues, in one transaction. False if the status was not allowed."""
        with self.r.pipeline() as pipe:
            while True:
                try:
                    pipe.watch(keys.job(job_id))
                    status = pipe.hget(keys.job(job_id), "status")
                    if status is None or Status(status.decode()) not in allowed:
                        return False
                    pipe.multi()
                    write(pipe)
                    pipe.execute()
                    return True
                except redis.WatchError:
                    continue

    def fail(self, job_id: str, message: str) -> None:
        arrays = self._arrays_of(job_id)

        def failed(pipe: redis.client.Pipeline) -> None:
            pipe.hset(keys.job(job_id), "error", message[:2000])
            self._finish(pipe, job_id, Status.FAILED, arrays, time.time())

        self._transition(job_id, policy.ACTIVE, failed)

    def cancel(self, job_id: str) -> Status | None:
        """Request cancellation; returns the resulting status. Batches no worker has taken
        are dropped at once, so a job with nothing rendering ends (and frees its slot) now;
        a worker that takes one of them later finds the job no longer rendering."""
        self._transition(job_id, policy.RENDERING,
                         lambda pipe: pipe.hset(keys.job(job_id), "status", Status.CANCEL_REQUESTED.value))
        for batch in self.leases.unowned(job_id):
            self.leases.drop(batch)
        self.settle(job_id, Status.CANCEL_REQUESTED, Status.CANCELLED)
        return self.status(job_id)

    # -------------------------------------------------------------------- merge
    def merge(self, batch: Batch, delta: Delta, seconds: float) -> str:
        """Add a batch's delta exactly once. Returns 'merged', 'duplicate' or 'inactive'.
        Read the state, merge, decide the job's status, write: one transaction."""
        key = keys.job(batch.job_id)
        merge_start = time.perf_counter()
        with self.r.lock(keys.merge_lock(batch.job_id), timeout=60, blocking_timeout=120):
            # The lock serialises one job's merges (saves re-reads); correctness comes from WATCH.
            while True:
                try:
                    with self.r.pipeline() as pipe:
                        pipe.watch(keys.version(batch.job_id), key)
                        # Read.
                        record = JobRecord.parse(batch.job_id, pipe.hgetall(key))
                        if pipe.sismember(keys.merged(batch.job_id), batch.id):
                            outcome = "duplicate"
                            break
                        if record.status not in policy.MERGING:
                            outcome = "inactive"
                            break
                        state = self.state(record)
                        # Merge.
                        integrator = record.integrator
                        integrator.merge(state, delta)
                        # Decide.
                        estimate = integrator.estimate(state)
                        error = estimate.average if estimate is not None else None
                        now = time.time()
                        elapsed = record.elapsed_seconds(now)
                        status = policy.after_merge(record.status, record.settings, state.passes, elapsed, error)
                        per_pass = seconds / batch.n
                        fields: dict[str, Any] = {
                            "passes": state.passes, "emitted": state.emitted, "status": status.value,
                            "pass_seconds": per_pass if record.pass_seconds == 0 else
                            0.7 * record.pass_seconds + 0.3 * per_pass,
                            "render_seconds": record.render_seconds + seconds, "merges": record.merges + 1,
                            **{COUNTER + name: value for name, value in state.counters.items()}}
                        if status != record.status:
                            fields["finished"] = now
                        # Write.
                        pipe.multi()
                        pipe.mset({keys.array(batch.job_id, name): array.tobytes()
                                   for name, array in state.arrays().items() if name not in integrator.setup_arrays})
                        pipe.hset(key, mapping=fields)
                        pipe.rpush(keys.history(batch.job_id), json.dumps(
                            {"passes": state.passes, "photons": state.emitted, "seconds": round(elapsed, 3),
                             "error": error}))
                        pipe.sadd(keys.merged(batch.job_id), batch.id)
                        Leases.release(pipe, batch)
                        pipe.incr(keys.version(batch.job_id))
                        if status in policy.FINAL:  # last: SET clears a key's time to live
                            self._finish(pipe, batch.job_id, status, tuple(integrator.state_widths), now)
                        pipe.execute()
                        outcome = "merged"
                        break
                except redis.WatchError:
                    continue
        if outcome != "merged":
            self.drop(batch)
        else:  # the merge's own cost: lock wait, read, add, write
            self.r.hincrbyfloat(key, "merge_seconds", time.perf_counter() - merge_start)
        return outcome
