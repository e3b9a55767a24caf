"""A state node's restart loses the pending deltas it held (they stay out of its append-only
file, worker/store/state.py): the next round finds them missing, the batches are issued
again under their ids, and their refills make every tile fold each batch once; the record
counts each once throughout. A job's end waits for its refills; a cancelled job takes its
lost batches back. Real redis-servers (the embedded default), restarted by SIGKILL."""

from __future__ import annotations

import pickle
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from service.redis_server import EmbeddedRedis
from tests.embedded_redis import redis_servers, restart
from tests.helpers import SHARDS, assert_folded_once, caustics_job, merge_new, sharded_store
from worker.config import Config
from worker.integrators.base import Delta
from worker.scheduler import reap
from worker.store import Batch, Jobs, keys
from worker.store.policy import Status

RESTARTED = 1  # the state node restarted (server 1 + RESTARTED)


@pytest.fixture
def servers(tmp_path: Path) -> Iterator[list[EmbeddedRedis]]:  # per test: the tests restart servers
    with redis_servers(tmp_path, 1 + SHARDS) as started:
        yield started


def _lose_deltas_of(servers: list[EmbeddedRedis], sample: tuple, pending: int,
                    max_passes: int = 1000) -> tuple[Jobs, str, list[Delta], list[Batch]]:
    """A job with two batches of `sample` (the `deltas` fixture) folded on every tile and
    `pending` more accepted, not folded; then a state node restarts. Returns the store, the
    job, its deltas and the pending batches."""
    made: list[Delta] = pickle.loads(sample[0].read_bytes())[:2 + pending]
    store = sharded_store([s.url for s in servers])
    job_id = caustics_job(store, *sample[1:], max_passes=max_passes)
    for d in made[:2]:
        merge_new(store, job_id, d)
    store.fold(job_id, wait=True, checkpoint=True)
    for d in made[2:]:
        merge_new(store, job_id, d)
    tiling = store.tiling(store.get(job_id))
    node = store.tiles.nodes[RESTARTED]
    on_node = [k for k in range(tiling.count) if tiling.node(k) == RESTARTED]
    assert all(node.hlen(keys.tile(job_id, k, "pending")) == pending for k in on_node)
    restart(servers[1 + RESTARTED])
    assert not any(node.exists(keys.tile(job_id, k, "pending")) for k in on_node)  # not in its append-only file
    assert node.scard(keys.tile(job_id, on_node[0], "folded")) == 2  # the checkpoint is
    return store, job_id, made, [Batch(job_id, d.first_pass, d.n_passes) for d in made[2:]]


def test_deltas_a_restart_lost_are_rendered_again_and_fold_once(servers: list[EmbeddedRedis],
                                                                deltas: tuple) -> None:
    store, job_id, made, lost = _lose_deltas_of(servers, deltas, pending=2)
    assert store.fold(job_id) is None  # the round finds them missing and writes nothing
    assert store.r.smembers(keys.lost(job_id)) == {b.id.encode() for b in lost}
    record = store.get(job_id)
    assert (record.passes, record.folded_passes) == (8, 4)  # still counted, once
    # Issued again: the reaper enqueues them at once, a worker may take them, and a round folds
    # the others meanwhile (here none).
    assert all(store.is_wanted(b) for b in lost)
    assert reap(store) == len(lost)
    for batch, d in zip(lost, made[2:], strict=True):
        assert store.start(batch, "w1")
        assert store.merge(batch, d, 0.1) == "refilled"  # the same passes and seeds (here the same delta)
        assert store.merge(batch, d, 0.1) == "duplicate"
    assert not store.r.exists(keys.lost(job_id)) and not store.leases.inflight(job_id)
    assert store.get(job_id).passes == 8
    assert_folded_once(store, job_id, made)  # the state is the sum of the deltas: each once on every tile


def test_a_jobs_end_waits_for_its_lost_batches(servers: list[EmbeddedRedis], deltas: tuple,
                                               tune: Callable[..., Config]) -> None:
    tune(end_handoff_seconds=0.2)  # no API: the worker ends the job
    store, job_id, made, lost = _lose_deltas_of(servers, deltas, pending=1, max_passes=8)
    last = pickle.loads(deltas[0].read_bytes())[3]
    merge_new(store, job_id, last)  # the budget's last batch: its end's round finds batch 2 lost
    record = store.get(job_id)
    assert record.status == Status.RUNNING and record.ending == Status.COMPLETED and not record.stopping
    assert store.r.smembers(keys.lost(job_id)) == {lost[0].id.encode()}
    assert not store.end_if_decided(job_id)  # the folder waits for the refill
    assert store.start(lost[0], "w1") and store.merge(lost[0], made[2], 0.1) == "refilled"
    assert store.status(job_id) == Status.COMPLETED  # the refill handed the end off
    assert_folded_once(store, job_id, [*made, last])


@pytest.mark.parametrize("issued_again", [True, False], ids=["found-before", "found-by-its-last-round"])
def test_a_cancelled_job_takes_its_lost_batches_back(servers: list[EmbeddedRedis], deltas: tuple,
                                                     issued_again: bool) -> None:
    store, job_id, made, lost = _lose_deltas_of(servers, deltas, pending=2)
    if issued_again:
        assert store.fold(job_id) is None and store.leases.inflight(job_id) == 2
    assert store.cancel(job_id) == Status.CANCELLED
    record = store.get(job_id)
    assert record.passes == record.folded_passes == 4 and record.emitted == record.folded_emitted
    assert store.r.smembers(keys.merged(job_id)) == {Batch(job_id, d.first_pass, d.n_passes).id.encode()
                                                     for d in made[:2]}
    assert not store.r.exists(keys.lost(job_id)) and not store.leases.inflight(job_id)
    assert not store.start(lost[0], "w1")
