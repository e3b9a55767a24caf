"""`photonfarm worker`: an RQ worker for render batches, on this or any machine that
reaches the Redis server. It needs nothing but the Redis URL: scenes travel inline.

SimpleWorker runs every batch in this process (no fork), so the OpenCL context and
compiled kernels live across batches. A lost Redis connection (a Redis restart) is not
fatal: the worker waits and reconnects; its batch in flight, if any, is re-issued by
the reaper when its lease expires.
"""

from __future__ import annotations

import logging
import os
import socket
import time
import uuid

import redis
from rq import Queue, SimpleWorker

from worker.heartbeat import Heartbeat
from worker.logs import configure_logging
from worker.scheduler import QUEUE_NAMES
from worker.store import Leases

log = logging.getLogger("photonfarm.worker")


def run_worker(redis_url: str, burst: bool = False) -> int:
    configure_logging()
    conn = redis.Redis.from_url(redis_url)
    while True:
        name = f"{socket.gethostname()}.{os.getpid()}.{uuid.uuid4().hex[:6]}"  # says where it runs
        beat = Heartbeat(Leases(conn), name).start()
        try:
            queues = [Queue(q, connection=conn) for q in QUEUE_NAMES]
            SimpleWorker(queues, connection=conn, name=name).work(burst=burst, with_scheduler=False)
            return 0
        except (redis.ConnectionError, redis.TimeoutError, redis.BusyLoadingError) as exc:
            log.warning("redis unavailable; retrying in 1 s: %s", exc)
            time.sleep(1.0)
        finally:
            beat.stop()
