"""Putting batches on the RQ queues, keeping jobs fed, and re-issuing lost batches.

Every job keeps about as many batches in flight as there are workers. A batch that merges
asks for the next one, which joins the END of its priority queue: batches of different
jobs interleave, so a small job never waits for a large one to finish, only for the
batches already queued. Workers take the high queue first, then normal, then low.

The reaper (run by the API process, every few seconds) looks at leases that expired:
a batch still waiting in a queue gets more time; one whose worker vanished (killed, or
its Redis connection lost) is put on the queue again. Its passes keep their indices and
seeds, and the merged set guarantees they count once whichever copy finishes first.
"""

from __future__ import annotations

import uuid

import redis
from rq import Queue, Worker
from rq.exceptions import NoSuchJobError
from rq.job import Job, JobStatus
from rq.serializers import JSONSerializer

from worker.job_store import ACTIVE, PRIORITIES, QUEUE_NAMES, Batch, JobStore

MAX_INFLIGHT_PER_JOB = 8
RQ_TIMEOUT = 900  # seconds; a batch is sized to take about two


def queue_for(conn: redis.Redis, priority: str) -> Queue:
    return Queue(QUEUE_NAMES[PRIORITIES.index(priority)], connection=conn, serializer=JSONSerializer)


def enqueue(store: JobStore, batch: Batch, priority: str) -> None:
    rq_id = f"pf-{batch.job_id}-{batch.first}-{batch.n}-{uuid.uuid4().hex[:8]}"
    store.r.hset("pf:batch-rq", batch.member, rq_id)
    queue_for(store.r, priority).enqueue_call(
        "worker.tasks.run_batch", args=(batch.job_id, batch.first, batch.n), timeout=RQ_TIMEOUT,
        result_ttl=0, failure_ttl=86_400, job_id=rq_id)


def target_inflight(conn: redis.Redis) -> int:
    return max(1, min(MAX_INFLIGHT_PER_JOB, Worker.count(connection=conn)))


def feed(store: JobStore, job_id: str, pass_seconds: float | None = None) -> int:
    """Issue batches until the job has its share in flight; returns how many were issued."""
    meta = store.meta(job_id)
    if meta is None:
        return 0
    issued = 0
    target = target_inflight(store.r)
    while store.inflight(job_id) < target:
        batch = store.allocate(job_id, pass_seconds)
        if batch is None:
            break
        enqueue(store, batch, meta["priority"])
        issued += 1
    return issued


def reap(store: JobStore) -> int:
    """Re-issue lost batches and settle jobs that have nothing left in flight."""
    reissued = 0
    for batch in store.expired_leases():
        if not store.is_wanted(batch):
            store.drop_batch(batch)
            continue
        rq_id = store.r.hget("pf:batch-rq", batch.member)
        status = None
        if rq_id is not None:
            try:
                status = Job.fetch(rq_id.decode(), connection=store.r, serializer=JSONSerializer).get_status()
            except NoSuchJobError:
                status = None
        if status == JobStatus.QUEUED:
            store.extend_queued(batch)  # still waiting its turn
            continue
        meta = store.meta(batch.job_id)
        store.reissue(batch)
        enqueue(store, batch, meta["priority"] if meta else "normal")
        reissued += 1
    for job_id in store.job_ids():
        meta = store.meta(job_id)
        if meta is None or meta["status"] not in ACTIVE:
            continue
        if meta["status"] == "cancel-requested":
            store.settle_cancel(job_id)
        elif store.inflight(job_id) == 0 and feed(store, job_id) == 0 and meta["status"] == "running":
            store.finish_spent(job_id)  # budget spent and nothing left to merge
    return reissued
