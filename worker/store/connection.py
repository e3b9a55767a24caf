"""Redis connections of every photonfarm process, with one timeout policy.

A large job's state moves in pipelines of hundreds of megabytes, and with the append-only
file fsynced on every write a Redis taking such a pipeline can leave another client
waiting longer than redis-py's default 5 s. That wait is load, not a lost server: a
socket times out only after SOCKET_TIMEOUT (a server that went away closes the socket,
which fails at once).

Replies are parsed by hiredis (far less CPU than redis-py's Python parser); commands are
packed by redis-py's own serializer, which sends a large argument (a tile's delta) as it
is, where hiredis's packer copies it twice."""

from __future__ import annotations

from collections.abc import Mapping

import redis
from redis.connection import PythonRespSerializer
from redis.typing import EncodableT, FieldT

SOCKET_TIMEOUT = 120.0
HEALTH_CHECK_SECONDS = 10
PACK_CUTOFF = 6000  # bytes: smaller pieces of a command are joined into one write (redis-py's own cutoff)


Fields = dict[FieldT, EncodableT]  # a hash's fields as written (HSET's mapping)


def text(reply: object) -> str:
    """A Redis string reply as str. Our connections reply bytes (no decode_responses);
    redis-py types a reply as bytes or str, and a str passes as it is."""
    if isinstance(reply, bytes):
        return reply.decode()
    if isinstance(reply, str):
        return reply
    raise TypeError(f"expected a Redis string reply, got {type(reply).__name__}")


def binary(reply: object) -> bytes:
    """A Redis string reply that holds bytes (our connections reply bytes: no decode_responses)."""
    if isinstance(reply, bytes):
        return reply
    raise TypeError(f"expected a Redis bytes reply, got {type(reply).__name__}")


def text_hash(reply: Mapping[bytes, bytes] | Mapping[bytes | str, bytes | str]) -> dict[str, str]:
    """A Redis hash reply (HGETALL) with its fields and values as str."""
    return {text(k): text(v) for k, v in reply.items()}


def connect(url: str) -> redis.Redis:
    pool = redis.ConnectionPool.from_url(url, socket_timeout=SOCKET_TIMEOUT,
                                         health_check_interval=HEALTH_CHECK_SECONDS)
    pool.connection_kwargs["command_packer"] = PythonRespSerializer(PACK_CUTOFF, pool.get_encoder().encode)
    return redis.Redis(connection_pool=pool)
