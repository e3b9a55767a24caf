"""Each test module gets its own real cluster (api_tests/cluster.py); a test that needs only
the store gets its own embedded Redis."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from api_tests.cluster import Cluster
from tests.conftest import redis_url  # noqa: F401 - the fixture, defined once for both suites


@pytest.fixture(scope="module")
def cluster(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Cluster]:
    c = Cluster(tmp_path_factory.mktemp("cluster"))
    yield c
    c.close()
