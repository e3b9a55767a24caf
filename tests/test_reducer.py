"""The reducer (worker/reducer.py) on real redis-servers: one reducer owns a job under its
lease and a dead one's job passes to another within a lease; one reaper at a time; a fold
round publishes the image and estimate any API process serves (worker/store/published.py),
and an image a restart lost is made again from the tiles."""

from __future__ import annotations

import pickle
import time
from collections.abc import Callable, Iterator
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from service.redis_server import EmbeddedRedis
from tests.embedded_redis import redis_servers
from tests.helpers import SHARDS, caustics_job, merge_new, sharded_store
from worker.config import Config
from worker.integrators.base import Delta
from worker.reducer import Reducer, hold
from worker.store import keys


@pytest.fixture
def servers(tmp_path: Path) -> Iterator[list[EmbeddedRedis]]:
    with redis_servers(tmp_path, 1 + SHARDS) as started:
        yield started


def test_one_reducer_owns_a_job_and_a_dead_ones_job_passes_on(servers: list[EmbeddedRedis], deltas: tuple,
                                                               tune: Callable[..., Config]) -> None:
    tune(lease_seconds=1.0)
    urls = [s.url for s in servers]
    job_id = caustics_job(sharded_store(urls), *deltas[1:])
    first, second = Reducer(sharded_store(urls)), Reducer(sharded_store(urls))
    assert first.claim() == [job_id] and second.claim() == []
    assert hold(first._reaper) and not hold(second._reaper)  # one reaper at a time
    time.sleep(0.5)
    assert first.claim() == [job_id] and second.claim() == []  # renewed: still the first's
    time.sleep(1.2)  # the first stops renewing (it died): its lease lapses
    assert second.claim() == [job_id]
    assert first.claim() == []
    assert hold(second._reaper) and not hold(first._reaper)  # the reaper's lease passed on too
    second.stop()  # gives its leases up: the job is free at once
    assert first.claim() == [job_id]


def test_a_round_publishes_the_image_any_process_serves(servers: list[EmbeddedRedis], deltas: tuple) -> None:
    urls = [s.url for s in servers]
    store = sharded_store(urls)
    job_id = caustics_job(store, *deltas[1:])
    made: list[Delta] = pickle.loads(deltas[0].read_bytes())[:3]
    for d in made[:2]:
        merge_new(store, job_id, d)
    folded = store.fold(job_id, wait=True)
    record = store.get(job_id)
    reader = sharded_store(urls)  # another process: no overlay, no fold
    image = reader.published(record)
    assert image is not None and image.passes == record.image_passes == sum(d.n_passes for d in made[:2])
    assert image.emitted == folded.state.emitted and image.counters == folded.state.counters
    np.testing.assert_array_equal(image.rgb, record.integrator.image(folded.state).astype(np.float32))
    assert image.estimate is not None and image.estimate.average == folded.error
    np.testing.assert_array_equal(image.estimate.relative, folded.estimate.relative.astype(np.float32))
    # An older image (a stale fold racing the round) does not replace it.
    assert not store.images.publish(job_id, replace(image, passes=image.passes - 1, rgb=image.rgb * 0))
    assert reader.published(record).rgb.any()
    # Lost (a restart of the main Redis: it is outside the append-only file): made from the
    # state the tiles hold as folded (the batch accepted meanwhile waits for the next round).
    merge_new(store, job_id, made[2])
    store.r.delete(keys.image(job_id))
    again = reader.published(store.get(job_id))
    assert again is not None and (again.passes, again.emitted) == (image.passes, image.emitted)
    np.testing.assert_allclose(again.rgb, image.rgb, rtol=1e-6)
    folded = store.fold(job_id, wait=True)  # the next round publishes the batch
    assert reader.published(store.get(job_id)).passes == sum(d.n_passes for d in made) == folded.state.passes
