"""Real Redis servers for the tests (service/redis_server.py's embedded redis-server):
several for sharded job state, one holding some data for the tests of what it does with
its memory and files, and a restart by SIGKILL. No pytest here: api_tests/cluster.py, which
the benchmarks use, imports restart."""

from __future__ import annotations

import os
import signal
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import redis

from service.redis_server import EmbeddedRedis


@contextmanager
def redis_servers(base: Path, count: int) -> Iterator[list[EmbeddedRedis]]:
    """`count` redis-servers in directories under `base`; stopped after."""
    started = [EmbeddedRedis(base / f"redis{i}").start(supervise=False) for i in range(count)]
    try:
        yield started
    finally:
        for server in started:
            server.stop()


def restart(server: EmbeddedRedis) -> None:
    """SIGKILL a redis-server, then start it again on the same port and data."""
    server.proc.send_signal(signal.SIGKILL)
    server.proc.wait()
    server.start(supervise=False)


class _Configured(EmbeddedRedis):
    """The embedded Redis with configuration lines added (a test's knobs of the server)."""

    def __init__(self, data_dir: Path, extra: tuple[str, ...]) -> None:
        super().__init__(data_dir)
        self.extra = extra

    def _config(self) -> str:
        return super()._config() + "".join(line + "\n" for line in self.extra)


@contextmanager
def holding(data_dir: Path, blobs: int, blob_bytes: int,
            extra_config: tuple[str, ...] = ()) -> Iterator[tuple[EmbeddedRedis, redis.Redis]]:
    """An embedded Redis in `data_dir` with `blobs` random values of `blob_bytes` each,
    and a client; stopped on exit."""
    server = _Configured(data_dir, extra_config).start(supervise=False)
    try:
        client = redis.Redis.from_url(server.url)
        blob = os.urandom(blob_bytes)
        for k in range(blobs):
            client.set(f"x{k}", blob)
        yield server, client
    finally:
        server.stop()
