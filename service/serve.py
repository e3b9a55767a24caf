"""`photonfarm serve`: the API on uvicorn, with its embedded defaults.

Without a Redis URL it starts the embedded Redis (service/redis_server.py) with its data
in --data-dir, and N local worker processes (default: one per core) that share the cores
through POCL_MAX_PTHREAD_COUNT. Local workers that exit are started again.

SIGTERM (docker stop, systemd) and SIGINT stop everything: uvicorn shuts down gracefully
and then re-raises the signal, whose default action would end this process before it
stops its children; here the signal ends uvicorn.run with SystemExit instead, so the
workers stop (each finishes or abandons its batch) and then Redis.
"""

from __future__ import annotations

import logging
import os
import signal
import subprocess
import sys
import threading
from pathlib import Path
from types import FrameType

import uvicorn

from service.app import create_app
from service.child_process import spawn
from service.redis_server import EmbeddedRedis
from worker.logs import configure_logging

log = logging.getLogger("photonfarm.serve")
STOP_SECONDS = 10.0  # a worker that has not finished its batch by then is killed


class LocalWorkers:
    """N `photonfarm worker` processes, restarted if they die."""

    def __init__(self, redis_url: str, count: int) -> None:
        self.count = count
        threads = max(1, (os.cpu_count() or 1) // max(count, 1))
        # The URL carries the Redis password: environment, not argv (which any local user can read).
        self.env = {**os.environ, "POCL_MAX_PTHREAD_COUNT": str(threads), "REDIS_URL": redis_url}
        self.procs: list[subprocess.Popen] = []
        self._stop = threading.Event()
        self._lock = threading.Lock()  # no restart once stop() began

    def _spawn(self) -> subprocess.Popen:
        return spawn([sys.executable, "-m", "service.cli", "worker"], env=self.env)

    def start(self) -> LocalWorkers:
        self.procs = [self._spawn() for _ in range(self.count)]
        threading.Thread(target=self._supervise, name="worker-supervisor", daemon=True).start()
        return self

    def _supervise(self) -> None:
        while not self._stop.wait(1.0):
            with self._lock:
                for i, proc in enumerate(self.procs):
                    if proc.poll() is not None and not self._stop.is_set():
                        log.warning("worker %d exited with %s; starting a new one", proc.pid, proc.returncode)
                        self.procs[i] = self._spawn()

    def stop(self) -> None:
        with self._lock:
            self._stop.set()
        for proc in self.procs:
            proc.terminate()
        for proc in self.procs:
            try:
                proc.wait(timeout=STOP_SECONDS)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


def _exit(signum: int, frame: FrameType | None) -> None:
    raise SystemExit(0)


def serve(host: str, port: int, workers: int | None, redis_url: str | None, data_dir: Path,
          token: str | None) -> int:
    configure_logging()
    signal.signal(signal.SIGTERM, _exit)  # uvicorn restores and re-raises it after its graceful shutdown
    signal.signal(signal.SIGINT, _exit)
    embedded = local = None
    try:
        if redis_url is None:
            embedded = EmbeddedRedis(data_dir / "redis").start()
            redis_url = embedded.url
            log.info("embedded redis at %s (password in %s)", embedded.public_url, data_dir / "redis")
        count = (os.cpu_count() or 1) if workers is None else workers
        local = LocalWorkers(redis_url, count).start() if count > 0 else None
        uvicorn.run(create_app(redis_url, token), host=host, port=port, log_level="info", log_config=None)
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_IGN)  # a second signal must not cut the cleanup short
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        if local is not None:
            local.stop()
        if embedded is not None:
            embedded.stop()
    return 0
