"""An embedded Redis (service/redis_server.py) holding some data, for the tests of what it
does with its memory and files."""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import redis

from service.redis_server import EmbeddedRedis


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
