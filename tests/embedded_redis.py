"""An embedded Redis (service/redis_server.py) holding some data, for the tests of what it
does with its memory and files."""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import redis

from service.redis_server import EmbeddedRedis


@contextmanager
def holding(data_dir: Path, blobs: int, blob_bytes: int) -> Iterator[tuple[EmbeddedRedis, redis.Redis]]:
    """An embedded Redis in `data_dir` with `blobs` random values of `blob_bytes` each,
    and a client; stopped on exit."""
    server = EmbeddedRedis(data_dir).start(supervise=False)
    try:
        client = redis.Redis.from_url(server.url)
        blob = os.urandom(blob_bytes)
        for k in range(blobs):
            client.set(f"x{k}", blob)
        yield server, client
    finally:
        server.stop()
