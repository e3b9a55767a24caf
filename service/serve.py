"""`photonfarm serve`: the API on uvicorn, with its embedded defaults.

Without a Redis URL it starts the embedded Redis (service/redis_server.py) with its data
in --data-dir; then --reducers reducer processes (default 1: they fold the jobs and
publish their images, worker/reducer.py) and N local worker processes (default: one per
core) that share the cores through POCL_MAX_PTHREAD_COUNT. Local processes that exit are
started again.

SIGTERM (docker stop, systemd) and SIGINT stop everything: uvicorn shuts down gracefully
and then re-raises the signal, whose default action would end this process before it
stops its children; here the signal ends uvicorn.run with SystemExit instead, so the
workers stop (each finishes or abandons its batch), then the reducers (each gives up its
jobs' leases), and then Redis.
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


class LocalProcesses:
    """N processes of one `photonfarm` command (worker, reducer), restarted if they die."""

    def __init__(self, command: str, redis_url: str, count: int, env: dict[str, str] | None = None) -> None:
        self.command, self.count = command, count
        # The URL carries the Redis password: environment, not argv (which any local user can read).
        self.env = {**os.environ, **(env or {}), "REDIS_URL": redis_url}
        self.procs: list[subprocess.Popen] = []
        self._stop = threading.Event()
        self._lock = threading.Lock()  # no restart once stop() began

    def _spawn(self) -> subprocess.Popen:
        return spawn([sys.executable, "-m", "service.cli", self.command], env=self.env)

    def start(self) -> LocalProcesses:
        self.procs = [self._spawn() for _ in range(self.count)]
        threading.Thread(target=self._supervise, name=f"{self.command}-supervisor", daemon=True).start()
        return self

    def _supervise(self) -> None:
        while not self._stop.wait(1.0):
            with self._lock:
                for i, proc in enumerate(self.procs):
                    if proc.poll() is not None and not self._stop.is_set():
                        log.warning("%s %d exited with %s; starting a new one", self.command, proc.pid,
                                    proc.returncode)
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


def local_workers(redis_url: str, count: int) -> LocalProcesses:
    """Workers that share the cores through POCL_MAX_PTHREAD_COUNT."""
    threads = max(1, (os.cpu_count() or 1) // max(count, 1))
    return LocalProcesses("worker", redis_url, count, {"POCL_MAX_PTHREAD_COUNT": str(threads)})


def _exit(signum: int, frame: FrameType | None) -> None:
    raise SystemExit(0)


def serve(host: str, port: int, workers: int | None, reducers: int, redis_url: str | None, data_dir: Path,
          token: str | None) -> int:
    configure_logging()
    signal.signal(signal.SIGTERM, _exit)  # uvicorn restores and re-raises it after its graceful shutdown
    signal.signal(signal.SIGINT, _exit)
    embedded = None
    children: list[LocalProcesses] = []  # stopped in reverse: the workers, then the reducers
    try:
        if redis_url is None:
            embedded = EmbeddedRedis(data_dir / "redis").start()
            redis_url = embedded.url
            log.info("embedded redis at %s (password in %s)", embedded.public_url, data_dir / "redis")
        if reducers > 0:
            children.append(LocalProcesses("reducer", redis_url, reducers).start())
        count = (os.cpu_count() or 1) if workers is None else workers
        if count > 0:
            children.append(local_workers(redis_url, count).start())
        uvicorn.run(create_app(redis_url, token), host=host, port=port, log_level="info", log_config=None)
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_IGN)  # a second signal must not cut the cleanup short
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        for local in reversed(children):
            local.stop()
        if embedded is not None:
            embedded.stop()
    return 0
