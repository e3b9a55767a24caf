"""Paced fold rounds on the real store (worker/store/record.py, Jobs.fold; the rule:
policy.paced_batches). Two batches accepted together while the job's next batch is in
flight, due far off, soon or overdue (it may come late): a regular round shows the lower
passes, the next round the rest, so the image changes twice; with nothing in flight, or in
a checkpoint round, one round takes both. The totals are exact either way. Real Redis, real
store."""

from __future__ import annotations

import time

import numpy as np
import pytest
import redis

from tests.helpers import running_job
from worker.config import config
from worker.integrators.base import Delta
from worker.store import Batch, Jobs, keys
from worker.store.leases import Leases
from worker.store.tiles import as_sent

W, H = 32, 16
TILE = 128  # 4 tiles
PHOTONS = 4096


@pytest.fixture()
def store(redis_url: str) -> Jobs:
    return Jobs(redis.Redis.from_url(redis_url), tile_pixels=TILE)


def _job_with_two_batches_waiting(store: Jobs, next_due_in: float | None) -> tuple[str, list[Delta]]:
    """A running job with batches 0+2 and 2+2 accepted and not folded, and batch 4+2 in
    flight, due `next_due_in` seconds from now (None: nothing in flight)."""
    job_id = running_job(store, W, H, started=time.time())
    record = store.get(job_id)
    n, widths = W * H, dict(record.integrator.sums.widths)
    rng = np.random.default_rng(3)
    deltas = [Delta(2 * b, 2, PHOTONS, {name: rng.uniform(0.5, 1.5, (n, w) if w > 1 else n)
                                        for name, w in widths.items()}) for b in range(2)]
    for d in deltas:
        assert store.merge(Batch(job_id, d.first_pass, 2), d, 0.01) == "merged"
    if next_due_in is not None:
        pipe = store.r.pipeline()
        Leases.register(pipe, Batch(job_id, 4, 2), time.time() + next_due_in)
        pipe.execute()
    return job_id, deltas


def _sum_of(store: Jobs, job_id: str, deltas: list[Delta]) -> np.ndarray:
    """The folded S of these deltas: the sum of each as sent."""
    record = store.get(job_id)
    return sum(as_sent(d.sums, store.tiling(record), record.integrator.sums.half)["S"] for d in deltas)


@pytest.mark.parametrize("next_due_in", [60.0, 1.0, -5.0])
def test_batches_that_came_together_show_over_two_rounds_while_one_is_in_flight(store: Jobs,
                                                                                next_due_in: float) -> None:
    job_id, deltas = _job_with_two_batches_waiting(store, next_due_in)
    first = store.fold(job_id)
    assert first is not None and first.state.passes == 2 and store.get(job_id).image_passes == 2
    np.testing.assert_allclose(first.state.S, _sum_of(store, job_id, deltas[:1]), rtol=1e-12)  # the lower passes first
    second = store.fold(job_id)
    assert second is not None and second.state.passes == 4 and store.get(job_id).image_passes == 4
    np.testing.assert_allclose(second.state.S, _sum_of(store, job_id, deltas), rtol=1e-12)
    assert store.fold(job_id) is None  # nothing left to show
    # The first round read the state from the tiles; the second added to the one it kept.
    assert [(r.batches, r.rebuilt) for r in store.get(job_id).fold_rounds] == [(1, True), (1, False)]


@pytest.mark.parametrize("next_due_in, checkpoint", [(None, False), (60.0, True)])
def test_one_round_takes_both_with_nothing_in_flight_or_at_a_checkpoint(store: Jobs, next_due_in: float | None,
                                                                        checkpoint: bool) -> None:
    job_id, deltas = _job_with_two_batches_waiting(store, next_due_in)
    folded = store.fold(job_id, checkpoint=checkpoint)
    assert folded is not None and folded.state.passes == 4 and store.get(job_id).image_passes == 4
    np.testing.assert_allclose(folded.state.S, _sum_of(store, job_id, deltas), rtol=1e-12)


def test_a_round_counts_its_checkpoint_writes_in_its_cost(store: Jobs) -> None:
    """A round's cost (JobRecord.fold_cost, what the batch and fold-interval rules count) is
    its whole length, the checkpoint written after its image included; a record deleted
    meanwhile is not brought back by noting it."""
    job_id, _ = _job_with_two_batches_waiting(store, next_due_in=60.0)
    assert store.fold(job_id, checkpoint=True) is not None
    record = store.get(job_id)
    assert record.round_cost > record.fold_seconds > 0.0
    assert record.fold_cost == record.round_cost
    store.delete(job_id)
    store.note_cost(job_id, 1.0)
    assert not store.r.exists(keys.job(job_id))


def test_the_folder_looks_again_when_a_round_is_due_not_a_whole_poll_later(store: Jobs,
                                                                           monkeypatch: pytest.MonkeyPatch) -> None:
    """reducer.next_look_in: the reducer waits until the first active job's next round is
    due (fold_interval after its last image), within fold_poll_seconds and never less than
    fold_wait_min_seconds; a job with no batch new to the image sets no wait."""
    from worker.reducer import next_look_in
    from worker.store import policy

    job_id, _ = _job_with_two_batches_waiting(store, next_due_in=60.0)
    assert store.fold(job_id) is not None  # the lower batch; the other waits for the next round
    record = store.get(job_id)
    monkeypatch.setattr(store, "active_ids", lambda: [job_id])  # other tests' jobs on this Redis aside
    interval = 0.4 + (time.time() - record.folded_at)
    monkeypatch.setattr(policy, "fold_interval", lambda *args: interval)  # due 0.4 s from now
    wait = next_look_in(store, store.active_ids())
    assert config().fold_wait_min_seconds < wait <= 0.4 < config().fold_poll_seconds
    assert store.fold_if_due(job_id) is None  # not yet
    time.sleep(wait)
    assert next_look_in(store, store.active_ids()) == config().fold_wait_min_seconds  # due now ...
    folded = store.fold_if_due(job_id)  # ... and folded at this look
    assert folded is not None and folded.state.passes == 4
    assert store.next_round_in(job_id) is None and next_look_in(store, store.active_ids()) == config().fold_poll_seconds
