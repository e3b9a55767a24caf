"""The batch-size rule (worker/store/policy.py, batch_passes): budgets first, then the merge share."""

from __future__ import annotations

import pytest

from worker.store.policy import (BATCH_TARGET_SECONDS, MAX_BATCH_PASSES, MERGE_SHARE, REFRESH_SECONDS,
                                 batch_passes)


def test_one_pass_until_a_pass_was_timed_and_none_when_no_pass_is_left() -> None:
    assert batch_passes(0.0, 0.0) == 1
    assert batch_passes(0.0, 0.0, passes_left=0) == 0
    assert batch_passes(0.5, 0.0, passes_left=0) == 0


def test_a_cheap_merge_gives_batches_of_the_target_length() -> None:
    assert batch_passes(0.25, 0.0) == round(BATCH_TARGET_SECONDS / 0.25)


def test_a_batch_is_long_enough_for_its_merge_and_fold_round_to_stay_within_the_share() -> None:
    n = batch_passes(0.5, 0.1, fold_seconds=0.2, workers=4)
    assert n * 0.5 == pytest.approx((0.1 + 0.2) / MERGE_SHARE, abs=0.5)


@pytest.mark.parametrize("workers", [1, 2, 3])
def test_the_workers_deliver_a_batch_every_refresh_interval_merges_included(workers: int) -> None:
    """A slow merge (a 3840x2160 frame) does not stretch batches past the refresh: the job's
    workers, each rendering a batch and then merging it, deliver one every REFRESH_SECONDS."""
    pass_seconds, merge = 1.0, 3.0
    n = batch_passes(pass_seconds, merge, fold_seconds=5.0, workers=workers)
    assert (n * pass_seconds + merge) / workers <= REFRESH_SECONDS + pass_seconds / 2
    assert n * pass_seconds >= workers * REFRESH_SECONDS - merge - pass_seconds  # and no shorter than that


def test_a_pass_longer_than_the_refresh_still_makes_a_batch_of_one() -> None:
    assert batch_passes(30.0, 5.0, fold_seconds=5.0) == 1


def test_the_time_budget_bounds_the_batch() -> None:
    assert batch_passes(1.0, 2.0, seconds_left=3.0, fold_seconds=2.0, workers=8) == 3


@pytest.mark.parametrize("workers, left", [(2, 10), (2, 7), (3, 10), (4, 3)])
def test_the_last_passes_are_split_among_the_workers(workers: int, left: int) -> None:
    """Near the end of a pass budget each batch takes at most its share of what is left,
    so the workers end together instead of one rendering the tail alone."""
    n = batch_passes(0.1, 0.0, workers=workers, passes_left=left)
    assert n == -(-left // workers)
    assert batch_passes(0.1, 0.0, workers=workers, passes_left=1000) == round(BATCH_TARGET_SECONDS / 0.1)


def test_batches_never_exceed_the_cap() -> None:
    assert batch_passes(0.001, 1.0, fold_seconds=10.0, workers=8) == MAX_BATCH_PASSES
