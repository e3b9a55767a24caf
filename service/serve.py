"""`photonfarm serve`: the API on uvicorn, with its embedded defaults.

Without a Redis URL it starts the embedded Redis (service/redis_server.py) with its data
in --data-dir, and N local worker processes (default: one per core) that share the cores
through POCL_MAX_PTHREAD_COUNT. Local workers that exit are started again.
"""

from __future__ import annotations

import logging
import os
import subprocess
import sys
import threading
from pathlib import Path

import uvicorn

from service.app import create_app
from service.child_process import spawn
from service.redis_server import EmbeddedRedis
from worker.logs import configure_logging

log = logging.getLogger("photonfarm.serve")


class LocalWorkers:
    """N `photonfarm worker` processes, restarted if they die."""

    def __init__(self, redis_url: str, count: int) -> None:
        self.redis_url = redis_url
        self.count = count
        threads = max(1, (os.cpu_count() or 1) // max(count, 1))
        self.env = {**os.environ, "POCL_MAX_PTHREAD_COUNT": str(threads)}
        self.procs: list[subprocess.Popen] = []
        self._stop = threading.Event()

    def _spawn(self) -> subprocess.Popen:
        return spawn([sys.executable, "-m", "service.cli", "worker", "--redis-url", self.redis_url], env=self.env)

    def start(self) -> "LocalWorkers":
        self.procs = [self._spawn() for _ in range(self.count)]
        threading.Thread(target=self._supervise, name="worker-supervisor", daemon=True).start()
        return self

    def _supervise(self) -> None:
        while not self._stop.wait(1.0):
            for i, proc in enumerate(self.procs):
                if proc.poll() is not None:
                    log.warning("worker %d exited with %s; starting a new one", proc.pid, proc.returncode)
                    self.procs[i] = self._spawn()

    def stop(self) -> None:
        self._stop.set()
        for proc in self.procs:
            proc.terminate()
        for proc in self.procs:
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                proc.kill()


def serve(host: str, port: int, workers: int | None, redis_url: str | None, data_dir: Path,
          token: str | None) -> int:
    configure_logging()
    embedded = None
    if redis_url is None:
        embedded = EmbeddedRedis(data_dir / "redis").start()
        redis_url = embedded.url
        log.info("embedded redis at %s (data in %s)", redis_url, data_dir / "redis")
    count = (os.cpu_count() or 1) if workers is None else workers
    local = LocalWorkers(redis_url, count).start() if count > 0 else None
    try:
        uvicorn.run(create_app(redis_url, token), host=host, port=port, log_level="info", log_config=None)
    finally:
        if local is not None:
            local.stop()
        if embedded is not None:
            embedded.stop()
    return 0
