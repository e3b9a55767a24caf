"""`photonfarm worker`: an RQ worker for render batches, on this or any machine that
reaches the Redis server. It needs nothing but the Redis URL (REDIS_URL, password
included): scenes travel inline.

SimpleWorker runs every batch in this process (no fork), so the OpenCL context and
compiled kernels live across batches. A lost Redis connection (a Redis restart) is not
fatal, wherever it strikes (RQ's own loop quits on errors it does not handle): the worker
waits (1, 2, 4 ... up to RETRY_MAX_SECONDS while Redis stays away) and starts its loop
again; its batch in flight, if any, is re-issued by the reaper when its lease expires. A
`--burst` worker, there to drain the queues and exit, gives up with exit status 1 once
Redis has been out of reach for BURST_PATIENCE_SECONDS (a wrong URL must not wait forever). A
worker asked to stop (SIGTERM, SIGINT) finishes or abandons its batch and exits; it never
goes on retrying a Redis that went away with it.

A worker runs at a lower CPU priority (nice NICE): where it shares a machine with the API
and Redis (`photonfarm serve` starts local workers), their fold rounds and requests
take the CPU when they need it, and the workers render with the rest (on a machine of
its own a worker loses nothing). Rounds that wait on Redis's own single thread it does not
speed up.

Job arguments travel as JSON (RQ's JSONSerializer: loading runs no code), and a worker
runs only the render task, whatever function or callbacks a job in the queue names.
"""

from __future__ import annotations

import logging
import os
import signal
import socket
import threading
import time
import uuid
from collections.abc import Callable
from types import FrameType
from typing import Any

import redis
from rq import Queue, SimpleWorker
from rq.job import Job
from rq.serializers import JSONSerializer

from worker.config import config
from worker.heartbeat import Heartbeat
from worker.logs import configure_logging
from worker.scheduler import QUEUE_NAMES
from worker.store import Leases
from worker.store.connection import connect

log = logging.getLogger("photonfarm.worker")
TASKS = ("worker.tasks.run_batch",)  # the only functions a queued job may name
RETRY_MAX_SECONDS = 8.0  # the longest wait between attempts to reach Redis (and so to resume after it)
BURST_PATIENCE_SECONDS = 20.0  # a --burst worker gives up once Redis has been out of reach this long


class BatchJob(Job):
    """An RQ job that resolves only to a photonfarm task, and to no callback.

    RQ imports by name the function a job names and its success, failure and stopped
    callbacks, all read from the job's Redis hash. A job that names anything but a task
    (or a method of an instance), or any callback, is refused before any name is imported:
    its function raises, so RQ files it as failed, and every callback resolves to none.
    """

    @property
    def func(self) -> Callable[..., Any]:
        named = [self._success_callback_name, self._failure_callback_name, self._stopped_callback_name]
        if self.func_name not in TASKS or self.instance is not None or any(named):
            raise ValueError(f"refusing to run {self.func_name!r} (callbacks {named}): not a photonfarm task")
        return super().func

    @property
    def success_callback(self) -> None:
        return None

    @property
    def failure_callback(self) -> None:
        return None

    @property
    def stopped_callback(self) -> None:
        return None


class BatchWorker(SimpleWorker):
    """SimpleWorker that remembers a stop request beyond its own work loop."""

    stopping = threading.Event()

    def request_stop(self, signum: int, frame: FrameType | None) -> None:
        BatchWorker.stopping.set()
        super().request_stop(signum, frame)


def _stop(signum: int, frame: FrameType | None) -> None:
    BatchWorker.stopping.set()


def _handle_stop_signals() -> None:
    """Between RQ work loops (RQ installs its own handlers inside one): just remember."""
    signal.signal(signal.SIGTERM, _stop)
    signal.signal(signal.SIGINT, _stop)


def run_worker(redis_url: str, burst: bool = False) -> int:
    configure_logging()
    os.nice(config().worker_nice)  # before any thread starts: the heartbeat and PoCL's threads inherit it
    conn = connect(redis_url)
    _handle_stop_signals()
    unreachable_since: float | None = None  # when Redis was first out of reach, this time
    wait = 1.0  # before the next attempt: doubles while Redis stays out of reach
    while not BatchWorker.stopping.is_set():
        name = f"{socket.gethostname()}.{os.getpid()}.{uuid.uuid4().hex[:6]}"  # says where it runs
        beat = Heartbeat(Leases(conn), name).start()
        try:
            queues = [Queue(q, connection=conn, job_class=BatchJob, serializer=JSONSerializer) for q in QUEUE_NAMES]
            BatchWorker(queues, connection=conn, name=name, job_class=BatchJob,
                        serializer=JSONSerializer).work(burst=burst, with_scheduler=False)
            if burst:
                return 0
            # RQ's loop also ends, logging it, on an error it does not handle (Redis gone while
            # it files a job's end among them): unless asked to stop, a new loop starts.
            reason, unreachable_since, wait = "its work loop ended", None, 1.0
        except (redis.ConnectionError, redis.TimeoutError, redis.BusyLoadingError) as exc:
            reason = f"redis unavailable: {exc}"
            unreachable_since = unreachable_since or time.monotonic()
        finally:
            beat.stop()
        _handle_stop_signals()
        if BatchWorker.stopping.is_set():
            break
        away = 0.0 if unreachable_since is None else time.monotonic() - unreachable_since
        if burst and away >= BURST_PATIENCE_SECONDS:
            log.error("%s; out of reach for %.0f s, so this --burst worker gives up", reason, away)
            return 1
        if burst and unreachable_since is not None:
            wait = min(wait, BURST_PATIENCE_SECONDS - away)  # one last attempt at the patience's end
        log.warning("%s; starting again in %.0f s", reason, wait)
        time.sleep(wait)
        if unreachable_since is not None:
            wait = min(RETRY_MAX_SECONDS, 2.0 * wait)
    log.info("stopped")
    return 0
