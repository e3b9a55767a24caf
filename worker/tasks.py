"""The RQ job a worker runs: one batch of passes of one render job, then its merge.

The worker process keeps its OpenCL context and one Engine per recent job (compiled
scene, uploaded buffers) across batches; RQ's SimpleWorker runs jobs in this process,
because OpenCL state does not survive a fork.
"""

from __future__ import annotations

import json
import logging
import time
from collections import OrderedDict

import pyopencl as cl
from rq import get_current_job

from kernels.program import create_context
from worker.engine import BatchAborted, Engine, RenderSettings
from worker.job_store import Batch, JobStore
from worker.scene import SCENES_DIR, SceneError, parse_scene
from worker.scheduler import feed

log = logging.getLogger("photonfarm.worker")
ENGINE_CACHE_SIZE = 2
_engines: "OrderedDict[str, Engine]" = OrderedDict()
_ctx: cl.Context | None = None


def engine_for(job_id: str, meta: dict[str, str]) -> Engine:
    """This process's Engine for a job, built on first use (scenes arrive inline in Redis)."""
    global _ctx
    if job_id in _engines:
        _engines.move_to_end(job_id)
        return _engines[job_id]
    _ctx = _ctx or create_context()
    settings = json.loads(meta["settings"])
    engine = Engine(parse_scene(json.loads(meta["scene"])), SCENES_DIR,
                    RenderSettings(method=settings["method"], gather=settings["gather"],
                                   photons_per_pass=settings["photons_per_pass"], seed=settings["seed"],
                                   initial_radius=settings.get("initial_radius")),
                    resolution=(int(meta["width"]), int(meta["height"])), ctx=_ctx)
    _engines[job_id] = engine
    while len(_engines) > ENGINE_CACHE_SIZE:
        _engines.popitem(last=False)
    return engine


def run_batch(job_id: str, first: int, n: int) -> str:
    rq_job = get_current_job()
    store = JobStore(rq_job.connection)
    batch = Batch(job_id, first, n)
    worker = rq_job.worker_name or "worker"
    context = {"job": job_id, "batch": batch.id, "worker": worker}
    if not store.start_batch(batch, worker):
        log.info("batch skipped: merged or no longer wanted", extra=context)
        return "skipped"
    store.heartbeat(worker, job_id, batch.id)
    meta = store.meta(job_id)
    try:
        engine = engine_for(job_id, meta)
    except (SceneError, ValueError) as exc:
        store.fail(job_id, f"cannot render this scene: {exc}")
        store.drop_batch(batch)
        log.error("job failed: cannot render its scene", extra=context)
        return "failed"
    start = time.perf_counter()
    try:
        r0 = store.initial_radius(job_id)
        if r0 is None:  # the job's first batch fixes R0 (one eye pass)
            r0 = store.init_radius(job_id, engine.initial_radius())
        radius, bias = store.batch_inputs(job_id, r0, meta)
        delta = engine.run_batch(radius, first, n, bias=bias,
                                 keep_going=lambda k: store.renew_lease(batch, worker) == "running")
    except BatchAborted:
        store.drop_batch(batch)
        log.info("batch aborted: the job stopped wanting it", extra=context)
        return "aborted"
    except Exception as exc:  # noqa: BLE001 - counted, then RQ records the traceback
        log.exception("batch failed", extra=context)
        if store.record_failure(batch, f"batch {batch.id} failed: {exc!r}"):
            store.drop_batch(batch)
        raise
    seconds = time.perf_counter() - start
    outcome = store.merge(batch, delta, seconds)
    log.info("batch done", extra={**context, "outcome": outcome, "seconds": round(seconds, 3), "passes": n})
    if outcome == "merged":
        feed(store, job_id, pass_seconds=seconds / n)
    return outcome
