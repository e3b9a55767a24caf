"""Redis connections of every photonfarm process, with one timeout policy.

A large job's state moves in pipelines of hundreds of megabytes, and with the append-only
file fsynced on every write a Redis taking such a pipeline can leave another client
waiting longer than redis-py's default 5 s. That wait is load, not a lost server: a
socket times out only after SOCKET_TIMEOUT (a server that went away closes the socket,
which fails at once)."""

from __future__ import annotations

import redis

SOCKET_TIMEOUT = 120.0
HEALTH_CHECK_SECONDS = 10


def connect(url: str) -> redis.Redis:
    return redis.Redis.from_url(url, socket_timeout=SOCKET_TIMEOUT, health_check_interval=HEALTH_CHECK_SECONDS)
