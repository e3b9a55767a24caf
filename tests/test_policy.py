"""The job policy's batch sizing (worker/store/policy.py), pure functions."""

from __future__ import annotations

import pytest

from worker.store.policy import MAX_BATCH_PASSES, REFRESH_SECONDS, batch_passes, staggered


@pytest.mark.parametrize("workers", [2, 3, 5])
def test_batches_that_start_together_come_to_arrive_evenly(workers: int) -> None:
    """Workers whose first batches end together (a job's start): each next batch ends in
    the middle of the largest gap between the others' ends, so within a few batches they
    arrive one every length / workers, as the refresh rule assumes."""
    length = workers * REFRESH_SECONDS
    ends = [1.0] * workers  # every worker's batch ends at t = 1 s
    arrivals: list[float] = []
    for _ in range(20 * workers):
        w = min(range(workers), key=ends.__getitem__)
        now = ends[w]
        arrivals.append(now)
        ends[w] = now + staggered(length, [e - now for i, e in enumerate(ends) if i != w])
    gaps = [b - a for a, b in zip(arrivals, arrivals[1:])][-3 * workers:]
    assert max(gaps) <= length / workers * 1.05 and min(gaps) >= length / workers * 0.95, gaps


def test_staggering_never_lengthens_a_batch() -> None:
    for others in ([], [0.3], [5.0, 5.1], [19.9], [40.0]):
        assert 0.0 < staggered(20.0, others) <= 20.0


def test_batch_passes_one_until_timed_and_within_the_budget() -> None:
    assert batch_passes(0.0, 0.0) == 1
    assert batch_passes(0.1, 0.0, seconds_left=0.35) * 0.1 <= 0.35 + 0.1  # ends within the budget plus one pass
    assert batch_passes(0.01, 10.0) == MAX_BATCH_PASSES
    # two workers whose other batch ends in 1 s: this one ends half a period later
    assert batch_passes(1.0, 0.0, fold_seconds=10.0, workers=2, others_end=[1.0]) == 11
