"""A job's shared state in Redis: layout, batch allocation, leases, the exactly-once merge.

Layout (all keys under `pf:`):
    pf:jobs                     zset   job id -> creation time
    pf:job:{id}                 hash   status, scene, settings, width, height, counters, times
    pf:job:{id}:{R0,N,S,D,...}  string float64 arrays (worker/stats.py accumulators)
    pf:job:{id}:version         int    bumped by every merge; merges WATCH it
    pf:job:{id}:merged          set    batch ids already merged (exactly once)
    pf:job:{id}:history         list   JSON {passes, photons, seconds, error} after each merge
    pf:job:{id}:inflight        set    batch ids issued and not yet merged or dropped
    pf:leases                   zset   "job/first/n" -> deadline; expired and unmerged = re-issue
    pf:lease-owner              hash   "job/first/n" -> worker name
    pf:batch-rq                 hash   "job/first/n" -> id of the RQ job that carries it
    pf:worker:{name}            hash   heartbeat: host, pid, job, batch, passes, last_seen (expires)

A batch is a range of pass indices [first, first+n). Its seeds come from (job seed, pass
index), so a re-issued batch recomputes exactly the same passes, and the merged set makes
sure they count once. The merge is one MULTI/EXEC under WATCH of the version key: a
worker that dies before EXEC leaves nothing behind, and two concurrent merges cannot both
apply (the loser re-reads and retries).
"""

from __future__ import annotations

import json
import os
import time
import uuid
from dataclasses import dataclass
from typing import Any

import numpy as np
import redis

from worker.error_estimate import bias_estimate, estimate
from worker.stats import ADDITIVE, Accumulators, Delta, radius, zeros

ACTIVE = ("queued", "running", "cancel-requested")
FINAL = ("cancelled", "converged", "completed", "failed")
PRIORITIES = ("high", "normal", "low")
QUEUE_NAMES = tuple(f"photonfarm-{p}" for p in PRIORITIES)  # workers listen in this order

# A started batch must report a pass (or finish) this often, or it is taken for lost.
LEASE_SECONDS = float(os.environ.get("PHOTONFARM_LEASE_SECONDS", "30"))
QUEUED_SECONDS = 120.0  # how often the reaper looks again at a batch still waiting in a queue
BATCH_TARGET_SECONDS = 2.0  # passes per batch are chosen to take about this long, and ...
MERGE_SHARE = 0.05  # ... at least 1/MERGE_SHARE times the job's mean merge (128 bytes a pixel each way)
MAX_BATCH_PASSES = 32
MAX_ATTEMPTS = 3  # a batch that fails this often fails its job
ARRAYS = ("N", *ADDITIVE)  # every per-pixel array of the state but R0


def job_key(job_id: str) -> str:
    return f"pf:job:{job_id}"


def array_key(job_id: str, name: str) -> str:
    return f"pf:job:{job_id}:{name}"


@dataclass(frozen=True)
class Batch:
    job_id: str
    first: int
    n: int

    @property
    def id(self) -> str:
        return f"{self.first}+{self.n}"

    @property
    def member(self) -> str:
        return f"{self.job_id}/{self.first}/{self.n}"

    @classmethod
    def parse(cls, member: str) -> "Batch":
        job_id, first, n = member.split("/")
        return cls(job_id, int(first), int(n))


def _decode(h: dict[bytes, bytes]) -> dict[str, str]:
    return {k.decode(): v.decode() for k, v in h.items()}


class JobStore:
    """All reads and writes of job state go through here."""

    def __init__(self, conn: redis.Redis) -> None:
        self.r = conn

    # ------------------------------------------------------------------ jobs
    def create(self, scene: dict[str, Any], settings: dict[str, Any], width: int, height: int,
               scene_name: str | None) -> str:
        job_id = uuid.uuid4().hex[:16]
        now = time.time()
        fields = {"status": "queued", "scene": json.dumps(scene), "settings": json.dumps(settings),
                  "scene_name": scene_name or "", "width": width, "height": height, "created": now,
                  "passes": 0, "emitted": 0, "next_pass": 0, "priority": settings["priority"],
                  "pass_seconds": 0.0, "attempts": "{}"}
        pipe = self.r.pipeline()
        pipe.hset(job_key(job_id), mapping=fields)
        pipe.zadd("pf:jobs", {job_id: now})
        pipe.execute()
        return job_id

    def meta(self, job_id: str) -> dict[str, str] | None:
        h = self.r.hgetall(job_key(job_id))
        return _decode(h) if h else None

    def settings(self, meta: dict[str, str]) -> dict[str, Any]:
        return json.loads(meta["settings"])

    def job_ids(self) -> list[str]:
        return [j.decode() for j in self.r.zrange("pf:jobs", 0, -1)]

    def active_count(self) -> int:
        pipe = self.r.pipeline()
        for job_id in self.job_ids():
            pipe.hget(job_key(job_id), "status")
        return sum(1 for s in pipe.execute() if s is not None and s.decode() in ACTIVE)

    def workers_on(self, job_id: str) -> int:
        members = [f"{job_id}/{b.decode().replace('+', '/')}" for b in self.r.smembers(f"{job_key(job_id)}:inflight")]
        if not members:
            return 0
        now = time.time()
        pipe = self.r.pipeline()
        for m in members:
            pipe.zscore("pf:leases", m)
            pipe.hget("pf:lease-owner", m)
        out = pipe.execute()
        owners = {out[i + 1] for i in range(0, len(out), 2) if out[i] is not None and out[i] > now and out[i + 1]}
        return len(owners)

    # ---------------------------------------------------------------- arrays
    def _arrays(self, job_id: str, names: tuple[str, ...], n_pixels: int) -> dict[str, np.ndarray]:
        blobs = self.r.mget([array_key(job_id, name) for name in names])
        out = {}
        for name, blob in zip(names, blobs):
            empty = zeros(n_pixels, name)
            out[name] = np.frombuffer(blob, np.float64).reshape(empty.shape).copy() if blob else empty
        return out

    def accumulators(self, job_id: str, meta: dict[str, str] | None = None) -> Accumulators | None:
        """The job's state, or None before its first batch fixed R0."""
        meta = meta or self.meta(job_id)
        n = int(meta["width"]) * int(meta["height"])
        r0 = self.r.get(array_key(job_id, "R0"))
        if r0 is None:
            return None
        arrays = self._arrays(job_id, ARRAYS, n)
        return Accumulators(alpha=self.settings(meta)["alpha"], R0=np.frombuffer(r0, np.float64).copy(),
                            N=arrays.pop("N"), sums=arrays, emitted=int(meta["emitted"]), passes=int(meta["passes"]))

    def batch_inputs(self, job_id: str, r0: np.ndarray, meta: dict[str, str]) -> tuple[np.ndarray, np.ndarray]:
        """What a batch starting now needs: the current radii, and the current bias estimate
        that its per-pass variance samples subtract (reads N, D and G only)."""
        arrays = self._arrays(job_id, ("N", "D", "G"), len(r0))
        r = radius(r0, arrays["N"], arrays["D"])
        constant = json.loads(meta["settings"]).get("bias_constant", "taylor")
        return r, bias_estimate(r, arrays["G"], int(meta["emitted"]), constant)

    def initial_radius(self, job_id: str) -> np.ndarray | None:
        blob = self.r.get(array_key(job_id, "R0"))
        return np.frombuffer(blob, np.float64).copy() if blob is not None else None

    def history(self, job_id: str) -> list[dict[str, float]]:
        return [json.loads(x) for x in self.r.lrange(f"{job_key(job_id)}:history", 0, -1)]

    def last_error(self, job_id: str) -> dict[str, float] | None:
        last = self.r.lindex(f"{job_key(job_id)}:history", -1)
        return json.loads(last) if last else None

    def init_radius(self, job_id: str, r0: np.ndarray) -> np.ndarray:
        """Fix the job's initial radii once (first writer wins) and return the stored ones."""
        self.r.set(array_key(job_id, "R0"), np.ascontiguousarray(r0, np.float64).tobytes(), nx=True)
        return np.frombuffer(self.r.get(array_key(job_id, "R0")), np.float64).copy()

    # --------------------------------------------------------------- batches
    def allocate(self, job_id: str, pass_seconds: float | None = None) -> Batch | None:
        """Reserve the next range of passes, or None if the budget is spent."""
        key = job_key(job_id)
        while True:
            try:
                with self.r.pipeline() as pipe:
                    pipe.watch(key)
                    meta = _decode(pipe.hgetall(key))
                    if meta.get("status") not in ("queued", "running"):
                        return None
                    settings = json.loads(meta["settings"])
                    started = float(meta.get("started") or 0.0)
                    if settings.get("max_seconds") and started and time.time() - started >= settings["max_seconds"]:
                        return None
                    first = int(meta["next_pass"])
                    per_pass = pass_seconds or float(meta["pass_seconds"])
                    merges = int(meta.get("merges", 0))
                    mean_merge = float(meta.get("merge_seconds", 0.0)) / merges if merges else 0.0
                    target = max(BATCH_TARGET_SECONDS, mean_merge / MERGE_SHARE)
                    n = max(1, min(MAX_BATCH_PASSES, round(target / per_pass))) if per_pass > 0 else 1
                    if settings.get("max_passes"):
                        n = min(n, settings["max_passes"] - first)
                    if n <= 0:
                        return None
                    batch = Batch(job_id, first, n)
                    pipe.multi()
                    pipe.hset(key, "next_pass", first + n)
                    pipe.sadd(f"{key}:inflight", batch.id)
                    pipe.zadd("pf:leases", {batch.member: time.time() + QUEUED_SECONDS})
                    pipe.execute()
                    return batch
            except redis.WatchError:
                continue

    def inflight(self, job_id: str) -> int:
        return self.r.scard(f"{job_key(job_id)}:inflight")

    def start_batch(self, batch: Batch, worker: str) -> bool:
        """Take the lease on a batch; False if it is no longer wanted."""
        key = job_key(batch.job_id)
        if self.r.sismember(f"{key}:merged", batch.id) or not self.r.sismember(f"{key}:inflight", batch.id):
            return False
        pipe = self.r.pipeline()
        pipe.zadd("pf:leases", {batch.member: time.time() + LEASE_SECONDS})
        pipe.hset("pf:lease-owner", batch.member, worker)
        pipe.execute()
        # queued -> running, and the clock starts, with the first batch that starts.
        with self.r.pipeline() as pipe:
            try:
                pipe.watch(key)
                if pipe.hget(key, "status") == b"queued":
                    pipe.multi()
                    pipe.hset(key, mapping={"status": "running", "started": time.time()})
                    pipe.execute()
            except redis.WatchError:
                pass  # someone else started it
        return True

    def renew_lease(self, batch: Batch, worker: str) -> str:
        """Called after every pass: extends the lease, beats the worker's heart, and
        returns the job's status (RQ's SimpleWorker sends no heartbeat during a job)."""
        pipe = self.r.pipeline()
        pipe.zadd("pf:leases", {batch.member: time.time() + LEASE_SECONDS}, xx=True)
        self._heartbeat(pipe, worker, batch.job_id, batch.id, passes=1)
        pipe.hget(job_key(batch.job_id), "status")
        status = pipe.execute()[-1]
        return status.decode() if status else "missing"

    def _heartbeat(self, pipe: redis.client.Pipeline, worker: str, job: str, batch: str, passes: int = 0) -> None:
        key = f"pf:worker:{worker}"
        pipe.hset(key, mapping={"job": job, "batch": batch, "last_seen": time.time()})
        pipe.hincrby(key, "passes", passes)
        pipe.expire(key, int(3 * LEASE_SECONDS))

    def heartbeat(self, worker: str, job: str = "", batch: str = "") -> None:
        pipe = self.r.pipeline()
        self._heartbeat(pipe, worker, job, batch)
        pipe.execute()

    def heartbeats(self) -> dict[str, dict[str, str]]:
        """worker name -> its last heartbeat (job, batch, passes, last_seen)."""
        keys = [k.decode() for k in self.r.scan_iter("pf:worker:*")]
        pipe = self.r.pipeline()
        for k in keys:
            pipe.hgetall(k)
        return {k.split(":", 2)[2]: _decode(h) for k, h in zip(keys, pipe.execute()) if h}

    def drop_batch(self, batch: Batch) -> None:
        """Forget a batch that will not be merged (its job ended or was cancelled)."""
        pipe = self.r.pipeline()
        pipe.srem(f"{job_key(batch.job_id)}:inflight", batch.id)
        pipe.zrem("pf:leases", batch.member)
        pipe.hdel("pf:lease-owner", batch.member)
        pipe.hdel("pf:batch-rq", batch.member)
        pipe.execute()
        self.settle_cancel(batch.job_id)

    def _settle(self, job_id: str, status: str, final: str) -> None:
        """A job in `status` with nothing in flight ends as `final` (atomically)."""
        key = job_key(job_id)
        with self.r.pipeline() as pipe:
            try:
                pipe.watch(key, f"{key}:inflight")
                if pipe.hget(key, "status") == status.encode() and pipe.scard(f"{key}:inflight") == 0:
                    pipe.multi()
                    pipe.hset(key, mapping={"status": final, "finished": time.time()})
                    pipe.execute()
            except redis.WatchError:
                pass  # something changed meanwhile: the next merge or reap decides

    def settle_cancel(self, job_id: str) -> None:
        """A cancel-requested job with nothing in flight is cancelled."""
        self._settle(job_id, "cancel-requested", "cancelled")

    def record_failure(self, batch: Batch, message: str) -> bool:
        """Count a failed attempt; after MAX_ATTEMPTS the job fails. True if it failed."""
        key = job_key(batch.job_id)
        attempts = json.loads(self.r.hget(key, "attempts") or b"{}")
        attempts[batch.id] = attempts.get(batch.id, 0) + 1
        self.r.hset(key, "attempts", json.dumps(attempts))
        if attempts[batch.id] >= MAX_ATTEMPTS:
            self.fail(batch.job_id, message)
            return True
        return False

    def fail(self, job_id: str, message: str) -> None:
        key = job_key(job_id)
        if (self.r.hget(key, "status") or b"").decode() in ACTIVE:
            self.r.hset(key, mapping={"status": "failed", "error": message[:2000], "finished": time.time()})

    def finish_spent(self, job_id: str) -> None:
        """A running job whose budget is spent and with nothing in flight is completed."""
        self._settle(job_id, "running", "completed")

    def cancel(self, job_id: str) -> str:
        """Request cancellation; returns the resulting status."""
        key = job_key(job_id)
        with self.r.pipeline() as pipe:
            while True:
                try:
                    pipe.watch(key)
                    status = (pipe.hget(key, "status") or b"").decode()
                    if status in ("queued", "running"):
                        pipe.multi()
                        pipe.hset(key, "status", "cancel-requested")
                        pipe.execute()
                    break
                except redis.WatchError:
                    continue
        self.settle_cancel(job_id)
        return (self.r.hget(key, "status") or b"").decode()

    # ------------------------------------------------------------------ merge
    def merge(self, batch: Batch, delta: Delta, seconds: float) -> str:
        """Add a batch's delta exactly once. Returns 'merged', 'duplicate' or 'inactive'.

        After the merge, inside the same transaction, the job ends if a budget is spent.
        """
        key = job_key(batch.job_id)
        version = f"{key}:version"
        merge_start = time.perf_counter()
        lock = self.r.lock(f"{key}:merge-lock", timeout=60, blocking_timeout=120)
        with lock:  # serialises merges of one job (saves re-reads); correctness comes from WATCH
            while True:
                try:
                    with self.r.pipeline() as pipe:
                        pipe.watch(version)
                        meta = _decode(self.r.hgetall(key))
                        if self.r.sismember(f"{key}:merged", batch.id):
                            outcome = "duplicate"
                            break
                        if meta.get("status") not in ("running", "cancel-requested"):
                            outcome = "inactive"
                            break
                        state = self.accumulators(batch.job_id, meta)
                        state.merge(delta)
                        settings = json.loads(meta["settings"])
                        now = time.time()
                        error = estimate(state, settings["confidence"], settings["bias_constant"]).average
                        status = meta["status"]
                        if status == "cancel-requested":
                            status = "cancelled"
                        elif settings.get("error_threshold") and error <= settings["error_threshold"]:
                            status = "converged"
                        elif settings.get("max_passes") and state.passes >= settings["max_passes"]:
                            status = "completed"
                        elif settings.get("max_seconds") and now - float(meta["started"]) >= settings["max_seconds"]:
                            status = "completed"
                        old = float(meta["pass_seconds"])
                        per_pass = seconds / batch.n
                        fields: dict[str, Any] = {
                            "passes": state.passes, "emitted": state.emitted, "status": status,
                            "pass_seconds": per_pass if old == 0 else 0.7 * old + 0.3 * per_pass,
                            "render_seconds": float(meta.get("render_seconds", 0.0)) + seconds,
                            "merges": int(meta.get("merges", 0)) + 1}
                        if status != meta["status"]:
                            fields["finished"] = now
                        pipe.multi()
                        arrays = {"N": state.N, **state.sums}
                        pipe.mset({array_key(batch.job_id, name): arrays[name].tobytes() for name in ARRAYS})
                        pipe.hset(key, mapping=fields)
                        pipe.rpush(f"{key}:history", json.dumps(
                            {"passes": state.passes, "photons": state.emitted,
                             "seconds": round(now - float(meta["started"]), 3), "error": error}))
                        pipe.sadd(f"{key}:merged", batch.id)
                        pipe.srem(f"{key}:inflight", batch.id)
                        pipe.zrem("pf:leases", batch.member)
                        pipe.hdel("pf:lease-owner", batch.member)
                        pipe.hdel("pf:batch-rq", batch.member)
                        pipe.incr(version)
                        pipe.execute()
                        outcome = "merged"
                        break
                except redis.WatchError:
                    continue
        if outcome != "merged":
            self.drop_batch(batch)
        else:  # the merge's own cost: lock wait, read, add, write
            self.r.hincrbyfloat(key, "merge_seconds", time.perf_counter() - merge_start)
        return outcome

    # ---------------------------------------------------------------- reaping
    def expired_leases(self, now: float | None = None) -> list[Batch]:
        now = time.time() if now is None else now
        return [Batch.parse(m.decode()) for m in self.r.zrangebyscore("pf:leases", "-inf", now)]

    def extend_queued(self, batch: Batch) -> None:
        self.r.zadd("pf:leases", {batch.member: time.time() + QUEUED_SECONDS}, xx=True)

    def reissue(self, batch: Batch) -> None:
        """Give a lost batch a fresh deadline (the caller enqueues it again)."""
        pipe = self.r.pipeline()
        pipe.zadd("pf:leases", {batch.member: time.time() + QUEUED_SECONDS})
        pipe.hdel("pf:lease-owner", batch.member)
        pipe.execute()

    def is_wanted(self, batch: Batch) -> bool:
        key = job_key(batch.job_id)
        status = (self.r.hget(key, "status") or b"").decode()
        return status in ("queued", "running") and not self.r.sismember(f"{key}:merged", batch.id) \
            and bool(self.r.sismember(f"{key}:inflight", batch.id))


def photons_per_second(meta: dict[str, str]) -> float:
    elapsed = elapsed_seconds(meta)
    return int(meta["emitted"]) / elapsed if elapsed > 0 else 0.0


def elapsed_seconds(meta: dict[str, str]) -> float:
    started = float(meta.get("started") or 0.0)
    if not started:
        return 0.0
    end = float(meta.get("finished") or 0.0) or time.time()
    return max(0.0, end - started)
