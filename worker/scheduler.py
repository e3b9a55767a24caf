"""Putting batches on the RQ queues, keeping jobs fed, and re-issuing lost batches.

Every job keeps about as many batches in flight as there are workers. A batch that merges
asks for the next one, which joins the END of its priority queue: batches of different
jobs interleave, so a small job never waits for a large one to finish, only for the
batches already queued. Workers take the high queue first, then normal, then low.

The reducers (worker/reducer.py) fold every active job's accepted batches into its state
(worker/store/state.py); one of them at a time reaps: it looks at leases that expired:
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

from worker.config import config
from worker.settings import PRIORITIES, Priority
from worker.store import Batch, Jobs, Status
from worker.store.policy import ACTIVE

QUEUE_NAMES = tuple(f"photonfarm-{p}" for p in PRIORITIES)  # workers listen in this order
RQ_TIMEOUT = 900  # seconds; a batch is sized to take about two


def queue_for(conn: redis.Redis, priority: Priority) -> Queue:
    return Queue(QUEUE_NAMES[PRIORITIES.index(priority)], connection=conn, serializer=JSONSerializer)


def enqueue(jobs: Jobs, batch: Batch, priority: Priority) -> None:
    rq_id = f"pf-{batch.job_id}-{batch.first}-{batch.n}-{uuid.uuid4().hex[:8]}"
    jobs.leases.set_carrier(batch, rq_id)
    queue_for(jobs.r, priority).enqueue_call(
        "worker.tasks.run_batch", args=(batch.job_id, batch.first, batch.n), timeout=RQ_TIMEOUT,
        result_ttl=0, failure_ttl=86_400, job_id=rq_id)


def target_inflight(jobs: Jobs) -> int:
    """Batches a job keeps in flight: one per live worker (dead registrations count for
    nothing), within max_inflight_per_job."""
    return max(1, min(config().max_inflight_per_job, jobs.leases.live_workers()))


def feed(jobs: Jobs, job_id: str, pass_seconds: float | None = None) -> int:
    """Issue batches until the job has its share in flight; returns how many were issued."""
    record = jobs.get(job_id)
    if record is None:
        return 0
    issued = 0
    target = target_inflight(jobs)
    while jobs.leases.inflight(job_id) < target:
        batch = jobs.allocate(job_id, pass_seconds, workers=target)
        if batch is None:
            break
        enqueue(jobs, batch, record.settings.priority)
        issued += 1
    return issued


def _still_queued(jobs: Jobs, batch: Batch) -> bool:
    """The batch's RQ job is waiting in its queue. A job RQ marks queued but that is in no
    queue list was taken by a worker that died before starting it: lost, not waiting."""
    rq_id = jobs.leases.carrier(batch)
    if rq_id is None:
        return False
    try:
        job = Job.fetch(rq_id, connection=jobs.r, serializer=JSONSerializer)
    except NoSuchJobError:
        return False
    return job.get_status() == JobStatus.QUEUED and \
        jobs.r.lpos(Queue(job.origin, connection=jobs.r, serializer=JSONSerializer).key, rq_id) is not None


def forget_dead_workers(jobs: Jobs) -> int:
    """Unregister from RQ the workers our heartbeat no longer hears (RQ keeps a worker that
    died mid-job registered until the job's timeout): they are no capacity."""
    dead = set(jobs.leases.dead_workers())
    if not dead:
        return 0
    for w in Worker.all(connection=jobs.r):
        if w.name in dead:
            w.register_death()
    return len(dead)


def reap(jobs: Jobs) -> int:
    """Re-issue lost batches and settle jobs that have nothing left in flight."""
    reissued = 0
    for batch in jobs.leases.expired():
        if not jobs.is_wanted(batch):
            jobs.drop(batch)
            continue
        if _still_queued(jobs, batch):
            jobs.leases.extend_queued(batch)  # still waiting its turn
            continue
        record = jobs.get(batch.job_id)
        jobs.leases.reissue(batch)
        enqueue(jobs, batch, record.settings.priority if record else "normal")
        reissued += 1
    forget_dead_workers(jobs)
    for job_id in jobs.active_ids():
        record = jobs.get(job_id)
        if record is None or record.status not in ACTIVE:
            continue
        if record.status == Status.CANCEL_REQUESTED:
            jobs.settle(job_id, Status.CANCEL_REQUESTED, Status.CANCELLED)
        elif jobs.leases.inflight(job_id) == 0 and feed(jobs, job_id) == 0 and record.status == Status.RUNNING:
            jobs.settle(job_id, Status.RUNNING, Status.COMPLETED)  # budget spent and nothing left to merge
    return reissued
