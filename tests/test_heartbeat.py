"""A worker's heartbeat while its Redis is away (worker/heartbeat.py): it beats on, warns
once when the outage starts (not at every beat), and says when Redis answers again; the
beats then reach the restarted server."""

from __future__ import annotations

import logging
import time

import redis

from service.redis_server import EmbeddedRedis
from worker.heartbeat import Heartbeat
from worker.store import Leases, keys

BEAT = 0.02  # seconds between beats: an outage of 1 s spans about 50


def test_an_outage_is_warned_once_and_its_end_is_told(tmp_path, caplog) -> None:
    server = EmbeddedRedis(tmp_path / "redis").start(supervise=False)
    port = server.port
    client = redis.Redis.from_url(server.url, socket_timeout=0.5, socket_connect_timeout=0.5)
    beat = Heartbeat(Leases(client), "w1", interval=BEAT)
    caplog.set_level(logging.INFO, logger="photonfarm.worker")
    beat.start()
    try:
        time.sleep(5 * BEAT)
        server.stop()
        time.sleep(1.0)  # some 50 beats find no Redis
        warnings = [r for r in caplog.records if r.levelno == logging.WARNING and "unavailable" in r.getMessage()]
        assert len(warnings) == 1, [r.getMessage() for r in warnings]
        server = EmbeddedRedis(tmp_path / "redis", port=port).start(supervise=False)  # same port and password
        client.delete(keys.worker("w1"))  # (the restarted server read its file: only a new beat may write this)
        deadline = time.monotonic() + 10.0
        while not client.exists(keys.worker("w1")) and time.monotonic() < deadline:
            time.sleep(BEAT)
        assert client.exists(keys.worker("w1"))
        deadline = time.monotonic() + 5.0
        while not any("reachable again" in r.getMessage() for r in caplog.records) and time.monotonic() < deadline:
            time.sleep(BEAT)
        assert any("reachable again" in r.getMessage() for r in caplog.records)
        warnings = [r for r in caplog.records if r.levelno == logging.WARNING and "unavailable" in r.getMessage()]
        assert len(warnings) == 1
    finally:
        beat.stop()
        server.stop()
