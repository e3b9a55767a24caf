"""Batch leases, the registry of issued batches, and worker heartbeats.

A batch is a range of pass indices [first, first + n) of one job. From its allocation
until it is merged or dropped it is in the job's in-flight set and holds a lease: a
deadline in `pf:leases`, queued_seconds while it waits in a queue, lease_seconds once a
worker has taken it (renewed after every pass). The registry also records which worker
owns it and which RQ job carries it, so the reaper (worker/scheduler.py) can tell a batch
still waiting from one whose worker vanished.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import redis

from worker.config import config
from worker.store import keys
from worker.store.connection import Fields, text, text_hash


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
    def parse(cls, member: str) -> Batch:
        job_id, first, n = member.split("/")
        return cls(job_id, int(first), int(n))

    @classmethod
    def from_id(cls, job_id: str, batch_id: str) -> Batch:
        first, n = batch_id.split("+")
        return cls(job_id, int(first), int(n))


class Leases:
    def __init__(self, conn: redis.Redis) -> None:
        self.r = conn

    # --------------------------------------------------------------- registry
    @staticmethod
    def register(pipe: redis.client.Pipeline, batch: Batch, due: float, queued: bool = True) -> None:
        """Queue the commands that issue a batch (inside the allocating transaction), expected
        to be delivered at `due` (epoch seconds). `queued`: the caller enqueues it, else its
        lease is lapsed at once and the reaper does (scheduler.reap)."""
        pipe.sadd(keys.inflight(batch.job_id), batch.id)
        pipe.zadd(keys.due(batch.job_id), {batch.id: due})
        pipe.zadd(keys.LEASES, {batch.member: time.time() + (config().queued_seconds if queued else 0.0)})

    @staticmethod
    def release(pipe: redis.client.Pipeline, batch: Batch) -> None:
        """Queue the commands that forget a batch (merged or dropped)."""
        pipe.srem(keys.inflight(batch.job_id), batch.id)
        pipe.zrem(keys.due(batch.job_id), batch.id)
        pipe.zrem(keys.LEASES, batch.member)
        pipe.hdel(keys.LEASE_OWNER, batch.member)
        pipe.hdel(keys.BATCH_RQ, batch.member)

    def drop(self, batch: Batch) -> None:
        pipe = self.r.pipeline()
        self.release(pipe, batch)
        pipe.execute()

    def inflight(self, job_id: str) -> int:
        return self.r.scard(keys.inflight(job_id))

    def inflight_batches(self, job_id: str) -> list[Batch]:
        return [Batch.from_id(job_id, text(b)) for b in self.r.smembers(keys.inflight(job_id))]

    def is_inflight(self, batch: Batch) -> bool:
        return bool(self.r.sismember(keys.inflight(batch.job_id), batch.id))

    def unowned(self, job_id: str) -> list[Batch]:
        """The job's in-flight batches that no worker has taken."""
        batches = self.inflight_batches(job_id)
        pipe = self.r.pipeline()
        for batch in batches:
            pipe.hexists(keys.LEASE_OWNER, batch.member)
        return [batch for batch, owned in zip(batches, pipe.execute(), strict=True) if not owned]

    def set_carrier(self, batch: Batch, rq_id: str) -> None:
        self.r.hset(keys.BATCH_RQ, batch.member, rq_id)

    def carrier(self, batch: Batch) -> str | None:
        rq_id = self.r.hget(keys.BATCH_RQ, batch.member)
        return text(rq_id) if rq_id is not None else None

    # ----------------------------------------------------------------- leases
    @staticmethod
    def take(pipe: redis.client.Pipeline, batch: Batch, worker: str) -> None:
        """Queue the commands that give `worker` the batch's lease (inside the starting transaction)."""
        pipe.zadd(keys.LEASES, {batch.member: time.time() + config().lease_seconds})
        pipe.hset(keys.LEASE_OWNER, batch.member, worker)

    def renew(self, pipe: redis.client.Pipeline, batch: Batch, worker: str) -> None:
        """Queue a lease extension and a heartbeat (after every pass)."""
        pipe.zadd(keys.LEASES, {batch.member: time.time() + config().lease_seconds}, xx=True)
        self._beat(pipe, worker, batch.job_id, batch.id, passes=1)

    def keep_alive(self, worker: str, batch: Batch | None) -> None:
        """The worker process's periodic beat (worker/heartbeat.py), with the lease of the
        batch it renders: a pass may take longer than a lease, a dead process beats no more."""
        pipe = self.r.pipeline()
        now = time.time()
        idle: Fields = {} if batch is not None else {"job": "", "batch": ""}  # an idle worker shows no job
        pipe.hset(keys.worker(worker), mapping={"last_seen": now, **idle})
        pipe.expire(keys.worker(worker), int(config().alive_seconds))
        pipe.zadd(keys.WORKER_SEEN, {worker: now})
        if batch is not None:
            pipe.zadd(keys.LEASES, {batch.member: now + config().lease_seconds}, xx=True)
        pipe.execute()

    def expired(self, now: float | None = None) -> list[Batch]:
        now = time.time() if now is None else now
        return [Batch.parse(text(m)) for m in self.r.zrangebyscore(keys.LEASES, "-inf", now)]

    def extend_queued(self, batch: Batch) -> None:
        self.r.zadd(keys.LEASES, {batch.member: time.time() + config().queued_seconds}, xx=True)

    def reissue(self, batch: Batch) -> None:
        """Give a lost batch a fresh deadline (the caller enqueues it again)."""
        pipe = self.r.pipeline()
        pipe.zadd(keys.LEASES, {batch.member: time.time() + config().queued_seconds})
        pipe.hdel(keys.LEASE_OWNER, batch.member)
        pipe.execute()

    def owners(self, job_id: str) -> int:
        """Workers holding a live lease on one of the job's batches."""
        members = [Batch.from_id(job_id, text(b)).member for b in self.r.smembers(keys.inflight(job_id))]
        if not members:
            return 0
        now = time.time()
        pipe = self.r.pipeline()
        for m in members:
            pipe.zscore(keys.LEASES, m)
            pipe.hget(keys.LEASE_OWNER, m)
        out = pipe.execute()
        return len({out[i + 1] for i in range(0, len(out), 2) if out[i] is not None and out[i] > now and out[i + 1]})

    # ------------------------------------------------------------- heartbeats
    @staticmethod
    def _beat(pipe: redis.client.Pipeline, worker: str, job: str, batch: str, passes: int = 0) -> None:
        key = keys.worker(worker)
        now = time.time()
        pipe.hset(key, mapping={"job": job, "batch": batch, "last_seen": now})
        pipe.hincrby(key, "passes", passes)
        pipe.expire(key, int(config().alive_seconds))
        pipe.zadd(keys.WORKER_SEEN, {worker: now})

    def live_workers(self) -> int:
        """Workers heard from within alive_seconds: the capacity batches are issued for."""
        return self.r.zcount(keys.WORKER_SEEN, time.time() - config().alive_seconds, "+inf")

    def dead_workers(self) -> list[str]:
        """Forget workers not heard from within alive_seconds; returns their names."""
        cutoff = time.time() - config().alive_seconds
        names = [text(n) for n in self.r.zrangebyscore(keys.WORKER_SEEN, "-inf", cutoff)]
        if names:
            self.r.zrem(keys.WORKER_SEEN, *names)
        return names

    def heartbeat(self, worker: str, job: str = "", batch: str = "") -> None:
        pipe = self.r.pipeline()
        self._beat(pipe, worker, job, batch)
        pipe.execute()

    def heartbeats(self) -> dict[str, dict[str, str]]:
        """Live worker name -> its last heartbeat (job, batch, passes, last_seen)."""
        names = [text(n) for n in self.r.zrangebyscore(keys.WORKER_SEEN, time.time() - config().alive_seconds, "+inf")]
        pipe = self.r.pipeline()
        for name in names:
            pipe.hgetall(keys.worker(name))
        return {name: text_hash(h) for name, h in zip(names, pipe.execute(), strict=True) if h}
