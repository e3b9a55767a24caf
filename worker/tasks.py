"""The RQ job a worker runs: one batch of passes of one render job, then its merge.

The worker process keeps its OpenCL context and one Engine per recent job (compiled
scene, uploaded buffers) across batches; RQ's SimpleWorker runs jobs in this process,
because OpenCL state does not survive a fork.
"""

from __future__ import annotations

import logging
import time
from collections import OrderedDict

import pyopencl as cl
import redis
from rq import get_current_job

from kernels.program import create_context
from worker.engine import Engine
from worker.heartbeat import holding
from worker.integrators.base import BatchAborted
from worker.scene import SCENES_DIR, SceneError, collector_paused, parse_scene
from worker.scheduler import feed
from worker.store import Batch, JobRecord, Jobs, Status
from worker.store.policy import recent_pass_seconds

log = logging.getLogger("photonfarm.worker")
ENGINE_CACHE_SIZE = 2
_engines: OrderedDict[str, Engine] = OrderedDict()
_ctx: cl.Context | None = None


def engine_for(jobs: Jobs, record: JobRecord) -> Engine:
    """This process's Engine for a job, built on first use (scenes arrive inline in Redis)."""
    global _ctx
    if record.id in _engines:
        _engines.move_to_end(record.id)
        return _engines[record.id]
    _ctx = _ctx or create_context()
    settings = record.settings.model_copy(update={"resolution": (record.width, record.height)})
    with collector_paused():
        scene = parse_scene(jobs.scene(record.id))
    engine = Engine(scene, SCENES_DIR, settings, ctx=_ctx)
    _engines[record.id] = engine
    while len(_engines) > ENGINE_CACHE_SIZE:
        _engines.popitem(last=False)
    return engine


def run_batch(job_id: str, first: int, n: int) -> str:
    rq_job = get_current_job()
    assert rq_job is not None, "run_batch runs only as an RQ job"
    jobs = Jobs(rq_job.connection)
    batch = Batch(job_id, first, n)
    worker = rq_job.worker_name or "worker"
    context = {"job": job_id, "batch": batch.id, "worker": worker}
    # Take the lease.
    if not jobs.start(batch, worker):
        log.info("batch skipped: merged or no longer wanted", extra=context)
        return "skipped"
    taken = time.perf_counter()
    record = jobs.get(job_id)
    assert record is not None, "a job whose batch was just leased has a record"
    try:
        with holding(batch):  # a first build (scene, kernels) may outlast a lease
            engine = engine_for(jobs, record)
    except (SceneError, ValueError) as exc:
        jobs.fail(job_id, f"cannot render this scene: {exc}")
        jobs.drop(batch)
        log.error("job failed: cannot render its scene", extra=context)
        return "failed"
    # Render: the job's first batch fixes its setup arrays (e.g. R0, from pass 0); the
    # passes alone are timed, each pass's end too (the next batch is sized by the later ones).
    pass_ends: list[float] = []

    def keep_going(k: int) -> bool:
        pass_ends.append(time.perf_counter())
        return jobs.renew(batch, worker) == Status.RUNNING

    try:
        with holding(batch):
            if not jobs.has_setup(record):
                jobs.init_setup(record, engine.passes.setup())
            start, cpu = time.perf_counter(), time.process_time()
            delta = engine.run_batch(jobs.batch_inputs(record), first, n, keep_going=keep_going)
    except BatchAborted:
        jobs.drop(batch)
        log.info("batch aborted: the job stopped wanting it", extra=context)
        return "aborted"
    except Exception as exc:  # counted, then RQ records the traceback
        log.exception("batch failed", extra=context)
        if jobs.record_failure(batch, f"batch {batch.id} failed: {exc!r}"):
            jobs.drop(batch)
        raise
    seconds, cpu_seconds = time.perf_counter() - start, time.process_time() - cpu
    # Merge, then ask for the next batch. The heartbeat keeps the lease while the delta is
    # pushed: a push may outlast a lease (half a GB at 3840x2160, a slow state node), and a
    # lapsed lease has the reaper issue the batch again for another worker to render in vain.
    with holding(batch):
        outcome = jobs.merge(batch, delta, seconds, wall_seconds=time.perf_counter() - taken, cpu_seconds=cpu_seconds)
    log.info("batch done", extra={**context, "outcome": outcome, "seconds": round(seconds, 3), "passes": n})
    if outcome in ("merged", "refilled"):
        feed(jobs, job_id, pass_seconds=recent_pass_seconds(start, pass_ends))
        try:
            jobs.fold_if_stale(job_id)
        except redis.RedisError as exc:  # the batch counts; the next fold takes it
            log.warning("fold failed: %s", exc, extra=context)
    return outcome
