"""The batch-size rule (worker/store/policy.py, batch_passes): budgets first, then the merge share;
the deliveries of a job's batches spread over the refresh interval; when a fold round starts
(fold_interval, round_seconds) and which waiting batches it takes in (paced_batches); the
tiles a fold round writes (checkpoint_tiles)."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import pytest

from worker.config import config
from worker.store.policy import (
    Round,
    _tail_end,
    batch_passes,
    checkpoint_required,
    checkpoint_seconds,
    checkpoint_tiles,
    fold_interval,
    image_due,
    paced_batches,
    recent_pass_seconds,
    round_seconds,
    tail_share,
)


def test_one_pass_until_a_pass_was_timed_and_none_when_no_pass_is_left() -> None:
    assert batch_passes(0.0, 0.0) == 1
    assert batch_passes(0.0, 0.0, passes_left=0) == 0
    assert batch_passes(0.5, 0.0, passes_left=0) == 0


def test_the_next_batch_is_sized_by_the_later_passes_of_the_last() -> None:
    """A batch's first pass carries its set-up, and a job's passes speed up as its radii
    shrink: the later half of the batch's passes, not its mean, predicts the next pass."""
    start, passes = 100.0, [3.8, 2.6, 2.4, 2.2, 2.0, 1.9]  # seconds each
    ends = list(start + np.cumsum(passes))
    assert recent_pass_seconds(start, ends) == pytest.approx((2.2 + 2.0 + 1.9) / 3)
    assert recent_pass_seconds(start, ends[:1]) == pytest.approx(3.8)  # one pass: all there is
    assert recent_pass_seconds(start, ends[:2]) == pytest.approx(2.6)


def test_a_cheap_merge_gives_batches_of_the_target_length() -> None:
    assert batch_passes(0.25, 0.0) == round(config().batch_target_seconds / 0.25)


def test_a_batch_is_long_enough_for_its_merge_and_fold_round_to_stay_within_the_share() -> None:
    n = batch_passes(0.5, 0.1, fold_seconds=0.2, workers=4)
    assert n * 0.5 == pytest.approx((0.1 + 0.2) / config().merge_share, abs=0.5)


@pytest.mark.parametrize("workers", [1, 2, 3])
def test_the_workers_deliver_a_batch_every_refresh_interval_merges_included(workers: int) -> None:
    """A slow merge (a 3840x2160 frame) does not stretch batches past the refresh: the job's
    workers, each rendering a batch and then merging it, deliver one every delivery_seconds
    even pass_slack slower than planned, and batches are no shorter than that allows."""
    pass_seconds, merge = 1.0, 3.0
    slower = 1.0 + config().pass_slack
    spread = [i * config().delivery_seconds / slower for i in range(1, workers)]  # the others due, spread
    n = batch_passes(pass_seconds, merge, fold_seconds=5.0, workers=workers, others_due=spread)
    assert (n * pass_seconds + merge) * slower / workers <= config().delivery_seconds + 1e-9
    assert ((n + 1) * pass_seconds + merge) * slower / workers > config().delivery_seconds  # and no shorter than that


def test_a_pass_longer_than_the_refresh_still_makes_a_batch_of_one() -> None:
    assert batch_passes(30.0, 5.0, fold_seconds=5.0) == 1


def test_the_time_budget_bounds_the_batch() -> None:
    assert batch_passes(1.0, 2.0, seconds_left=3.0, fold_seconds=2.0, workers=8) == 3


@pytest.mark.parametrize("workers, left", [(2, 10), (2, 7), (3, 10), (4, 3)])
def test_the_last_passes_are_split_among_the_workers(workers: int, left: int) -> None:
    """Near the end of a pass budget, with every other worker free, each batch takes its
    share of what is left, so the workers end together instead of one rendering the tail alone."""
    n = batch_passes(0.1, 0.0, workers=workers, passes_left=left)
    assert n == -(-left // workers)
    assert batch_passes(0.1, 0.0, workers=workers, passes_left=1000) == round(config().batch_target_seconds / 0.1)


def test_the_tail_is_rounded_to_the_earlier_end() -> None:
    """15 passes left, the other worker's batch due in 7.1 s, 1.4 s a pass: the even end is
    10.04 passes off. Rounded up (11), this worker would end at 15.4 s and the other at
    12.7 s (4 passes); 10 ends both by 14.1 s."""
    assert tail_share(15, 1.4, 2, [7.1]) == 10
    assert tail_share(16, 1.4, 2, [7.1]) == 11  # 11 and 5: 15.4 and 14.1 s; 10 and 6 would end at 15.5 s


def test_the_tail_end_is_that_of_handing_out_passes_one_at_a_time() -> None:
    """_tail_end gives the others their passes in bulk (a tail of 10^6 passes on 100 workers
    costs what one of 10 does); the end is the same as a pass at a time to whichever is free
    first."""
    rng = np.random.default_rng(5)
    for _ in range(2000):
        due = sorted(rng.uniform(0.0, 10.0, rng.integers(1, 7)).tolist())
        pass_seconds, left = float(rng.uniform(0.1, 2.0)), int(rng.integers(1, 60))
        n = int(rng.integers(1, left + 1))
        free = list(due)
        for _ in range(left - n):
            free[free.index(min(free))] += pass_seconds
        assert _tail_end(n, left, pass_seconds, due) == pytest.approx(max([n * pass_seconds, *free]), abs=1e-9)


def _tail(workers: int, pass_seconds: float, merge: float, fold: float, total: int) -> tuple[list[int], list[float]]:
    """A job of `total` passes whose workers each allocate their next batch on delivering
    one (told the passes left and when the others' batches are due): its batches' passes and
    each worker's last delivery."""
    due: dict[int, float] = {}
    sizes: list[int] = []
    ends: dict[int, float] = {}

    def allocate(w: int, now: float) -> None:
        n = batch_passes(pass_seconds, merge, fold_seconds=fold, workers=workers, passes_left=total - sum(sizes),
                         others_due=[at - now for v, at in due.items() if v != w])
        if n > 0:
            due[w] = now + n * pass_seconds + merge
            sizes.append(n)

    for w in range(workers):
        allocate(w, 0.0)
    while due:
        w = min(due, key=lambda v: due[v])
        ends[w] = due.pop(w)
        allocate(w, ends[w])
    return sizes, list(ends.values())


@pytest.mark.parametrize("workers, pass_seconds, merge, fold, total", [
    (2, 1.8, 0.3, 0.7, 80), (2, 0.33, 0.05, 0.05, 90), (3, 1.0, 0.3, 0.6, 100), (5, 1.1, 0.3, 0.6, 300)])
def test_the_workers_end_a_pass_budget_together_in_few_batches(workers: int, pass_seconds: float, merge: float,
                                                               fold: float, total: int) -> None:
    """The last passes go to the free worker and to the others once their batches are due,
    so that all end together: at most about two passes apart, and the tail adds at most one
    batch per worker to what batches of the usual length would take (an equal split of
    what is left, blind to the others' batches, halves the tail batch by batch: 8, 4, 2, 1)."""
    sizes, ends = _tail(workers, pass_seconds, merge, fold, total)
    assert sum(sizes) == total
    assert max(ends) - min(ends) <= 2 * pass_seconds + merge
    usual = max(sizes)
    assert len(sizes) <= -(-total // usual) + workers, sizes


@pytest.mark.parametrize("workers", [20, 100, 1000])
def test_many_workers_on_a_job_load_its_merge_path_the_same(workers: int) -> None:
    """With many workers the refresh asks little of a batch's length: the merge share sets
    it (a 1920x1080 pass of 1.2 s, a merge of 0.3 s and a fold round of 2.4 s: 46 passes,
    whatever that takes in passes), and past some N the job's merges together, which come
    N / batch a second, would keep its merge path ever busier: batches then lengthen with N,
    so the path is busy at most merge_path_share of the time, and the image still changes
    every refresh_seconds."""
    pass_seconds, merge, fold = 1.2, 0.3, 2.4
    spread = [i * config().refresh_seconds / 2 for i in range(1, workers)]  # the others' deliveries, spread
    batch = batch_passes(pass_seconds, merge, fold_seconds=fold, workers=workers, others_due=spread) * pass_seconds
    assert batch >= (merge + fold) / config().merge_share - pass_seconds / 2
    assert workers / (batch + merge) * merge <= config().merge_path_share * 1.01
    assert (batch + merge) / workers <= config().refresh_seconds


class Delivery(NamedTuple):
    """A batch in a simulated job: when it was allocated, when it was due (the store's
    `due`, at the recent pace) and when it was delivered."""

    allocated: float
    due: float
    delivered: float


def _deliveries(workers: int, pass_seconds: float, merge: float, fold: float, horizon: float = 400.0,
                slower: float = 1.0) -> tuple[list[Delivery], list[int]]:
    """A job's batches, in order of delivery, and their passes when its workers start
    together (the feed's allocations, one after another) and each allocates its next batch
    on delivering one, told when the others' batches are due; each batch takes `slower`
    times what it was planned to (the pace that sized it is not the one it runs at)."""
    inflight: dict[int, Delivery] = {}
    sizes: list[int] = []

    def allocate(w: int, now: float) -> None:
        n = batch_passes(pass_seconds, merge, fold_seconds=fold, workers=workers,
                         others_due=[b.due - now for v, b in inflight.items() if v != w])
        planned = n * pass_seconds + merge
        inflight[w] = Delivery(now, now + planned, now + slower * planned)
        sizes.append(n)

    for w in range(workers):
        allocate(w, 0.0)
    deliveries: list[Delivery] = []
    while (w := min(inflight, key=lambda v: inflight[v].delivered)) is not None and \
            inflight[w].delivered < horizon:
        deliveries.append(inflight[w])
        allocate(w, inflight[w].delivered)
    return deliveries, sizes


@pytest.mark.parametrize("workers", [1, 2, 3, 5, 20, 100])
@pytest.mark.parametrize("pass_seconds, merge, fold", [(4.4, 1.0, 2.6), (1.1, 0.3, 0.6), (0.2, 0.05, 0.1),
                                                       (2.9, 2.0, 7.0)])
def test_workers_that_start_together_deliver_spread_over_the_refresh(workers: int, pass_seconds: float,
                                                                     merge: float, fold: float) -> None:
    """The job's deliveries are at most delivery_seconds apart (workers that start together
    would otherwise deliver together, a refresh of workers times the interval), and its
    batches stay about as long as with the others' deliveries evenly spread (the merge share)."""
    deliveries, sizes = _deliveries(workers, pass_seconds, merge, fold)
    gaps = np.diff([0.0] + [d.delivered for d in deliveries])
    assert gaps.max() <= config().delivery_seconds + 1e-9, gaps.max()
    spread = [i * config().refresh_seconds for i in range(1, workers)]
    assert np.mean(sizes[workers:]) >= 0.7 * batch_passes(pass_seconds, merge, fold_seconds=fold, workers=workers,
                                                          others_due=spread)


@pytest.mark.parametrize("fold", [0.05, 0.4, 2.6, 7.0])
def test_fold_rounds_end_within_the_refresh_of_each_other(fold: float) -> None:
    """A round starts at the folder's first look after fold_interval and takes `fold`."""
    assert fold_interval(fold) + config().fold_poll_seconds + fold <= config().refresh_seconds


def test_a_round_longer_than_the_last_still_ends_within_the_refresh() -> None:
    """A big frame's rounds: a fixed part and a part per new batch, 1 to 5 batches a round,
    each within 15% of that (the machine's load). Started at the folder's last look after
    fold_interval with the length round_seconds expects from the rounds before, at most 5%
    of them end later than refresh_seconds after the last (about 3% expected); with the last
    round's length in its place, a round that takes in more batches than the last ends late
    (about half of them)."""
    rng = np.random.default_rng(7)
    rounds: list[tuple[int, float]] = []
    late, late_by_last, timed = 0, 0, 0
    for _ in range(500):
        batches = int(rng.integers(1, 6))
        seconds = (1.5 + 0.8 * batches) * rng.uniform(0.85, 1.15)
        if len(rounds) >= config().rounds_kept:
            last, timed = rounds[-1][1], timed + 1
            expected = round_seconds(rounds[-config().rounds_kept:], batches)
            late += fold_interval(last, expected) + config().fold_poll_seconds + seconds > config().refresh_seconds
            late_by_last += fold_interval(last) + config().fold_poll_seconds + seconds > config().refresh_seconds
        rounds.append((batches, seconds))
    assert late <= 0.05 * timed, late
    assert late_by_last >= 0.3 * timed, late_by_last


def test_the_expected_round_follows_its_batches() -> None:
    """round_seconds recovers a fixed part and a part per batch from rounds that fit them
    exactly, takes a round as one batch's worth more than its batches with no spread in
    them, and expects nothing before the first round."""
    assert round_seconds([], 3) is None
    exact = [(b, 2.0 + 0.5 * b) for b in (1, 3, 2, 4)]
    assert round_seconds(exact, 6) == pytest.approx(5.0)
    assert round_seconds([(2, 3.0), (2, 3.0)], 5) == pytest.approx(6.0)


def test_a_rebuilt_round_does_not_set_the_next_rounds_start() -> None:
    """A round that rebuilt the state from the tiles (a 3840 x 2160 job's first: 8.2 s, then
    rounds of 1.6 s) is left out of the expected length: the next rounds still start so as
    to end about delivery_seconds after the last, not at once (with it in the fit, and its
    margin, a round was expected to take 14 s and started fold_seconds after the last)."""
    rounds = [Round(1, 8.2, True), Round(1, 1.6), Round(2, 2.1), Round(1, 1.7)]
    expected = round_seconds(rounds, 1)
    assert expected == pytest.approx(round_seconds(rounds[1:], 1)) and expected < 2.5
    assert fold_interval(rounds[-1].seconds, expected) > config().delivery_seconds - 2.5
    fit = round_seconds([(b, t) for b, t, _ in rounds], 1)  # the fit with it
    assert fold_interval(1.7, fit) == config().fold_seconds
    assert round_seconds([Round(1, 8.2, True)], 1) is None  # the last round's length stands in (fold_interval)


def test_a_round_takes_every_waiting_batch_unless_the_next_delivery_is_far() -> None:
    """paced_batches: one waiting batch, or nothing in flight: all of them; a delivery due
    already or soon enough for the image to change within delivery_seconds: all but one (it
    may come late); a far delivery: an even share over the rounds that fit before it, at
    least one."""
    assert paced_batches(1, 60.0, 3.0) == 1
    assert paced_batches(1, -4.0, 3.0) == 1
    assert paced_batches(2, None, 3.0) == 2
    assert paced_batches(2, -4.0, 3.0) == 1
    assert paced_batches(100, 0.2, 3.0) == 99  # many workers: deliveries come all the time
    assert paced_batches(3, config().delivery_seconds - 3.0, 3.0) == 2
    assert paced_batches(2, 15.0, 3.0) == 1
    assert paced_batches(5, 15.0, 3.0) == 3  # 2 rounds fit: 3, then 2
    assert paced_batches(3, 100.0, 3.0) == 1


def _image_gaps(deliveries: list[Delivery], round_length: float, paced: bool) -> np.ndarray:
    """The folder's loop against a job's batches: it looks every fold_poll_seconds and starts
    a round once fold_interval has passed since the last one ended and a batch waits, told
    when the next batch in flight is due (paced_batches); the round takes `round_length` and
    the image changes at its end. Returns the intervals between image changes."""
    end = max(d.delivered for d in deliveries)
    waiting, images, free_at, t = 0, [], -np.inf, 0.0
    while t < end:
        waiting += sum(1 for d in deliveries if t - config().fold_poll_seconds < d.delivered <= t)
        if waiting and t >= free_at and (not images or t - images[-1] >= fold_interval(round_length, round_length)):
            next_due = min((d.due - t for d in deliveries if d.allocated <= t < d.delivered), default=None)
            take = paced_batches(waiting, next_due, round_length) if paced else waiting
            waiting -= take
            images.append(t + round_length)
            free_at = images[-1]
        t += config().fold_poll_seconds
    return np.diff(images)


def _in_step(cycle: float, workers: int = 2, apart: float = 0.05, cycles: int = 30) -> list[Delivery]:
    """Workers that each deliver a batch every `cycle` s, `apart` s after one another (in
    step: all between two looks of the folder), each batch due when it is delivered."""
    at = sorted(0.1 + c * cycle + apart * w for c in range(cycles) for w in range(workers))
    return [Delivery(t - cycle, t, t) for t in at]


@pytest.mark.parametrize("cycle", [12.0, 16.0, 19.0])
def test_paced_rounds_refresh_the_image_of_workers_in_step(cycle: float) -> None:
    """Two workers in step, a batch each every 12-19 s (a 3840x2160 pass on one core and its
    push), rounds of 3 s: taking in both batches at once leaves the image unchanged for the
    whole cycle; paced, it changes at most refresh_seconds apart."""
    assert _image_gaps(_in_step(cycle), 3.0, paced=False).max() >= cycle - config().fold_poll_seconds
    assert _image_gaps(_in_step(cycle), 3.0, paced=True).max() <= config().refresh_seconds


@pytest.mark.parametrize("workers", [2, 3])
@pytest.mark.parametrize("pass_seconds, merge, fold", [(7.3, 2.0, 1.8), (7.3, 1.5, 1.2), (4.4, 1.0, 2.6),
                                                       (1.6, 0.3, 0.7)])
def test_the_image_refreshes_while_every_batch_runs_slower_than_planned(workers: int, pass_seconds: float,
                                                                         merge: float, fold: float) -> None:
    """Workers that start together and whose batches, sized at the recent pace, all take
    pass_slack longer than planned (an append-only-file rewrite on their cores: 40-45% at
    3840x2160, 7.3 s a pass, a merge of 1.5-2 s): the folder's paced rounds still change the
    image every refresh_seconds. Batches sized to deliver exactly delivery_seconds apart
    (two 4K passes each on two workers) left it unchanged for 11-13 s here, and so did
    rounds that folded every waiting batch with a delivery in flight (12.5-13 s)."""
    deliveries, _ = _deliveries(workers, pass_seconds, merge, fold, slower=1.0 + config().pass_slack)
    assert _image_gaps(deliveries, fold, paced=True).max() <= config().refresh_seconds


def test_pacing_leaves_a_busy_job_alone() -> None:
    """Eight workers out of step, a delivery every 1.5 s: every round takes in all that wait."""
    busy = _in_step(12.0, workers=8, apart=1.5)
    assert np.array_equal(_image_gaps(busy, 3.0, paced=True), _image_gaps(busy, 3.0, paced=False))


def test_a_checkpoint_writes_a_part_of_the_state_each_round_and_keeps_the_pending_deltas_bounded() -> None:
    """policy.checkpoint_tiles under a big frame's load: each round adds a delta of about
    half the state's bytes to every tile. The deltas left pending stay within the share, each
    round writes a part of the state (never all of it, as one checkpoint every few rounds
    did), and every tile is written within a few rounds."""
    tiles, state, delta = 100, 128, 60
    state_bytes = {k: state for k in range(tiles)}
    pending = {k: 0 for k in range(tiles)}
    last_written = {k: 0 for k in range(tiles)}
    written_per_round = []
    for r in range(1, 41):
        pending = {k: p + delta for k, p in pending.items()}
        chosen = checkpoint_tiles(0.0, pending, state_bytes)
        assert len(set(chosen)) == len(chosen)
        for k in chosen:
            pending[k], last_written[k] = 0, r
        assert sum(pending.values()) <= config().checkpoint_pending_share * state * tiles
        assert all(r - last_written[k] <= 4 for k in range(tiles) if r > 4)
        written_per_round.append(len(chosen))
    steady = written_per_round[4:]
    assert max(steady) <= 0.6 * tiles and min(steady) >= 0.2 * tiles, written_per_round


def test_every_tile_with_a_pending_delta_is_written_once_a_batch_waited_too_long() -> None:
    pending, state_bytes = {0: 5, 1: 0, 2: 7}, {0: 100, 1: 100, 2: 100}
    assert checkpoint_tiles(0.0, pending, state_bytes) == []  # within the share
    assert sorted(checkpoint_tiles(config().checkpoint_seconds, pending, state_bytes)) == [0, 2]


@pytest.mark.parametrize("fold_seconds, fold_cost", [(0.05, 0.08), (0.5, 1.0), (1.8, 4.0), (3.5, 6.0)])
def test_a_worker_takes_the_api_to_be_behind_only_after_the_image_it_plans(fold_seconds: float,
                                                                           fold_cost: float) -> None:
    """policy.image_due bounds the longest a batch waits for the API's image when the API
    keeps its plan: accepted as a round read the waiting batches, it waits for that round's
    image, the fold interval after it and the next round (expected to take at most the
    last one's whole cost; at 3840x2160 about 2 s to the image, 4 s in all). The fold
    interval alone, the bound before, was shorter there: workers folded for a healthy API."""
    for expected in np.linspace(0.1 * fold_cost, fold_cost, 7):
        longest = fold_seconds + fold_interval(fold_cost, expected) + expected
        assert image_due(fold_seconds, fold_cost) >= longest - 1e-9
    c = config()
    assert image_due(fold_seconds, fold_cost) <= fold_seconds + max(c.fold_seconds + fold_cost, c.delivery_seconds)
    if fold_cost >= 4.0:  # 3840x2160: the old bound, stale-fold slack included, fell short of a paced round's image
        assert fold_interval(fold_cost) + config().fold_stale_seconds < \
            fold_seconds + fold_interval(fold_cost, 0.5 * fold_cost) + 0.5 * fold_cost


def test_a_round_writes_past_the_next_rounds_start_only_what_memory_asks() -> None:
    """checkpoint_required: the first of a round's tiles, in its order, that bring the pending
    deltas within checkpoint_held_share of the state's bytes (none when they are); the rest
    of its writes end when the next round must start for its image to come delivery_seconds
    after this one's (checkpoint_seconds, as fold_interval)."""
    state = {k: 100 for k in range(4)}
    cap = config().checkpoint_held_share * 400
    assert checkpoint_required([3, 1, 0, 2], {k: cap / 4 for k in range(4)}, state) == []
    over = {0: cap / 2, 1: cap / 2, 2: cap / 4, 3: cap / 4}  # 1.5 times the cap
    assert checkpoint_required([2, 0, 1, 3], over, state) == [2, 0]
    assert checkpoint_required([0, 2, 1, 3], over, state) == [0]
    assert checkpoint_seconds(2.0) == fold_interval(30.0, 2.0) == config().delivery_seconds - 2.0
    assert checkpoint_seconds(20.0) == 0.0
