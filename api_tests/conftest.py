"""Each test module gets its own real cluster (api_tests/cluster.py); a test that needs only
the store gets its own embedded Redis."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from api_tests.cluster import Cluster
from service.redis_server import EmbeddedRedis


@pytest.fixture(scope="module")
def cluster(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Cluster]:
    c = Cluster(tmp_path_factory.mktemp("cluster"))
    yield c
    c.close()


@pytest.fixture
def redis_url(tmp_path: Path) -> Iterator[str]:
    """A real embedded Redis of the test's own, stopped after it."""
    server = EmbeddedRedis(tmp_path / "redis").start(supervise=False)
    yield server.url
    server.stop()
