"""Each test module gets its own real cluster (api_tests/cluster.py)."""

from __future__ import annotations

from typing import Iterator

import pytest

from api_tests.cluster import Cluster


@pytest.fixture(scope="module")
def cluster(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Cluster]:
    c = Cluster(tmp_path_factory.mktemp("cluster"))
    yield c
    c.close()
