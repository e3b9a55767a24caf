"""The job policy, pure: statuses, how many passes a batch gets, and when a job ends.

No Redis here: the record (worker/store/record.py) reads the facts, asks these functions,
and writes what they decide.
"""

from __future__ import annotations

import heapq
import math
from collections.abc import Sequence
from enum import StrEnum
from typing import NamedTuple

from worker.config import config
from worker.settings import Settings


class Status(StrEnum):
    QUEUED = "queued"
    RUNNING = "running"
    CANCEL_REQUESTED = "cancel-requested"
    CANCELLED = "cancelled"
    CONVERGED = "converged"
    COMPLETED = "completed"
    FAILED = "failed"


ACTIVE = frozenset({Status.QUEUED, Status.RUNNING, Status.CANCEL_REQUESTED})  # holds a job slot
RENDERING = frozenset({Status.QUEUED, Status.RUNNING})  # takes new batches
MERGING = frozenset({Status.RUNNING, Status.CANCEL_REQUESTED})  # a finished batch still counts
FINAL = frozenset(Status) - ACTIVE

# The tunables this policy reads (the lease, the batch target and shares, the refresh, the
# fold's and checkpoints' timings) are fields of worker/config.py's Config, read at each call.


def batch_passes(pass_seconds: float, mean_merge_seconds: float, seconds_left: float | None = None,
                 fold_seconds: float = 0.0, workers: int = 1, passes_left: int | None = None,
                 others_due: Sequence[float] = ()) -> int:
    """Passes for the next batch of a job whose `workers` render its batches at once.

    Target: about batch_target_seconds, and at least what keeps the batch's merge plus the
    job's fold round (`fold_seconds`) within merge_share of a worker's time and the job's
    merges within merge_path_share of its merge path. Then bounded by
    - the refresh, over the merge shares (a budget beats a cost): the workers together
      deliver a batch every planned_delivery_seconds (merge included), each at most that
      long after the last of the job's other in-flight batches due before it
      (`others_due`, seconds from now), so that workers fall out of step;
    - the budgets, over everything: `seconds_left` (the job ends within it plus one pass)
      and `passes_left`, shared with the other in-flight batches so all end together
      (`tail_share`).
    At least one pass while the budgets allow; one while `pass_seconds` is unknown (0). No
    cap in passes: the refresh bounds a batch, and a worker asks after every pass whether
    the job still wants it."""
    workers, n, c = max(1, workers), 1, config()
    if pass_seconds > 0.0:
        # The bounds, in seconds at the recent pace: the refresh (planned deliveries, which
        # leave room for passes pass_slack slower), the cost (the merge shares), the budget.
        refresh = max(pass_seconds, workers * c.planned_delivery_seconds - mean_merge_seconds)
        cost = max((mean_merge_seconds + fold_seconds) / c.merge_share,
                   workers * mean_merge_seconds / c.merge_path_share)
        target = max(c.batch_target_seconds, min(cost, refresh))
        if seconds_left is not None:
            target = min(target, seconds_left)
        # Passes: the target's nearest count, but never past the refresh, nor past a delivery
        # planned_delivery_seconds after the last of the others due before this one.
        last = max((due for due in others_due if due < target + mean_merge_seconds), default=0.0)
        stagger = math.floor((max(0.0, last) + c.planned_delivery_seconds - mean_merge_seconds) / pass_seconds)
        n = max(1, min(round(target / pass_seconds), math.floor(refresh / pass_seconds), stagger))
    if passes_left is not None:
        n = min(n, tail_share(passes_left, pass_seconds, workers, others_due))
    return n


def recent_pass_seconds(start: float, pass_ends: Sequence[float]) -> float:
    """A worker's render seconds a pass for sizing its next batch, from its batch's start and
    each pass's end: the mean of the later half of the passes (at least the last). Not the
    batch's mean, which the first pass's set-up and the shrinking radii make overstate the
    next pass."""
    ends = [start, *pass_ends]
    later = max(1, (len(ends) - 1) // 2)
    return (ends[-1] - ends[-1 - later]) / later


def tail_share(passes_left: int, pass_seconds: float, workers: int, others_due: Sequence[float] = ()) -> int:
    """This batch's part of a job's last `passes_left` passes, so that its worker (free now)
    and the job's other `workers - 1` end together: each other worker renders from when its
    in-flight batch is due (`others_due`, seconds from now; one without a batch is free now),
    and all at `pass_seconds` a pass. The end T solves T + sum over the others of
    max(0, T - due) = passes_left * pass_seconds (filled in order of due time). This batch
    takes T / pass_seconds passes rounded up, or one fewer where that ends the job sooner
    (`_tail_end`: a pass is whole, so rounding up can leave this worker a pass behind the
    others). With every other worker free that is an equal split; with the others busy for
    long, more of the tail, in fewer batches (each batch costs a merge and a fold round
    whatever its passes). Untimed: an equal split."""
    others = max(1, workers) - 1
    if pass_seconds <= 0.0 or others == 0:
        return -(-passes_left // (others + 1))
    due = sorted(max(0.0, d) for d in others_due)[:others]
    due = [0.0] * (others - len(due)) + due  # workers without an in-flight batch are free now
    end = _fill_level(passes_left * pass_seconds, due, 1)
    n = min(passes_left, max(1, math.ceil(end / pass_seconds - 1e-6)))
    if n > 1 and _tail_end(n - 1, passes_left, pass_seconds, due) < _tail_end(n, passes_left, pass_seconds, due):
        return n - 1
    return n


def _fill_level(work: float, due: Sequence[float], free: int) -> float:
    """The end T at which `free` workers free now and the others, free from `due` (sorted),
    together finish `work` seconds of passes: T free + sum of max(0, T - d) = work."""
    end, started = 0.0, 0.0  # started: the sum of the first i dues (the workers busy until then)
    for i, d in enumerate([*due, math.inf]):
        if free + i > 0:
            end = (work + started) / (free + i)
            if end <= d:
                break
        started += d
    return end


def _tail_end(n: int, passes_left: int, pass_seconds: float, due: Sequence[float]) -> float:
    """When a job's last delivery comes if this batch takes `n` of its last `passes_left`
    passes and the other workers (free from `due`, sorted) the rest, each pass to whichever
    is free first: in bulk up to the level at which they would all be busy, then a pass at a
    time (fewer than one per worker)."""
    left = passes_left - n
    level = _fill_level(left * pass_seconds, due, 0)
    takes = [max(0, math.floor((level - d) / pass_seconds)) for d in due]
    free = [d + k * pass_seconds for d, k in zip(due, takes, strict=True)]
    heapq.heapify(free)
    for _ in range(left - sum(takes)):
        heapq.heapreplace(free, free[0] + pass_seconds)
    return max([n * pass_seconds, *free])


# ------------------------------------------------------------- the termination rule
def out_of_time(settings: Settings, elapsed: float) -> bool:
    return settings.max_seconds is not None and elapsed >= settings.max_seconds


def passes_left(settings: Settings, passes: int) -> int | None:
    """Passes the budget still allows after `passes` (None: no pass budget)."""
    return None if settings.max_passes is None else max(0, settings.max_passes - passes)


def fold_interval(fold_seconds: float, next_seconds: float | None = None) -> float:
    """Seconds from one fold round's image to the next one's start, given what the last
    round cost (`fold_seconds`: its whole length, checkpoint writes included,
    JobRecord.fold_cost) and how long the next is expected to take to its image
    (`next_seconds`, round_seconds; the last one's cost if unknown): fold_seconds for a
    small state; for a large one long enough that rounds take at most fold_share of the
    time (more batches folded per round), but short enough that the next round starts (at
    the folder's next look) and ends within refresh_seconds of the last one's end
    (`_start_by`)."""
    expected = fold_seconds if next_seconds is None else next_seconds
    c = config()
    return max(c.fold_seconds, min(fold_seconds / c.fold_share, _start_by(expected)))


def _start_by(next_seconds: float) -> float:
    """The latest, in seconds after a round's image, the next round starts for its image to
    come delivery_seconds after this one's, at its expected length (round_seconds, which has
    a margin for a round longer than the last: round_margin). Not with pass_slack: a round
    started earlier leaves the next one nothing to show until a delivery comes."""
    return config().delivery_seconds - next_seconds


def image_due(fold_seconds: float, fold_cost: float) -> float:
    """The latest the API plans the image that takes in a batch accepted as a round read the
    waiting batches, in seconds after that read: the round's length to its image
    (`fold_seconds`), the fold interval after it, and the next round's length (at most the
    whole cost of the last, `fold_cost`). Why all three: a paced round may end its image
    about delivery_seconds after the last, and a worker that took the API to be behind would
    fold in its place (a checkpoint of every tile, then a rebuilt state)."""
    return fold_seconds + fold_interval(fold_cost) + fold_cost


class Round(NamedTuple):
    """A fold round as the job record keeps it: the new batches it took in, its seconds to
    the image, and whether it rebuilt the job's state from the tiles (no state kept in the
    folder's memory: a job's first round, or the first after the folder restarted), which
    costs more than a round that adds to the kept state."""

    batches: int
    seconds: float
    rebuilt: bool = False


def round_seconds(rounds: Sequence[tuple], batches: int) -> float | None:
    """How long a fold round that takes in `batches` new batches is expected to run (to its
    image), from the job's recent rounds (Round, or (batches, seconds); rounds_kept of them)
    that added to a kept state: a round merges each new delta and then estimates the whole
    state, so it costs a part per batch and a fixed part, fit to those rounds by least
    squares (with no spread in their batches, the fixed part taken as one batch's), plus
    round_margin times the most any of them ran over the fit, so that a round longer than
    the last one still ends in time. None before any. A rebuilt round is left out: it reads
    every tile into fresh memory, costs several times a regular one, and would inflate the
    next rounds_kept predictions."""
    kept = [Round(*r) for r in rounds]
    kept = [r for r in kept if not r.rebuilt]
    if not kept:
        return None
    n = [float(r.batches) for r in kept]
    s = [r.seconds for r in kept]
    n_mean, s_mean = sum(n) / len(n), sum(s) / len(s)
    spread = sum((x - n_mean) ** 2 for x in n)
    covariance = sum((x - n_mean) * (y - s_mean) for x, y in zip(n, s, strict=True))
    per_batch = covariance / spread if spread else s_mean / (1 + n_mean)
    per_batch = max(0.0, per_batch)
    fixed = max(0.0, s_mean - per_batch * n_mean)
    over = max(y - (fixed + per_batch * x) for x, y in zip(n, s, strict=True))
    return fixed + per_batch * batches + config().round_margin * max(0.0, over)


# Pacing. Workers that render one long pass per batch deliver together, and a round that
# folds such a pair shows both at once and then nothing until the next pair. Pacing spreads
# the waiting batches over the rounds that fit before the next delivery (batches that
# arrive often enough are all folded at once), and while a batch is in flight a round keeps
# one back, since the next delivery may come pass_slack late: the held batch shows one round
# later, and that round has something new to show.
def paced_batches(waiting: int, next_delivery: float | None, round_length: float) -> int:
    """How many of the `waiting` batches new to the image a regular fold round takes in
    (the oldest first; the rest wait for the next rounds), given when the job's next batch
    is due (`next_delivery`, seconds from now, overdue below 0; None with none in flight)
    and the round's expected length: an even share of the rounds, delivery_seconds apart,
    that fit before the next delivery's, and all but one while a batch is in flight."""
    if next_delivery is None:
        return waiting
    rounds = max(1, min(waiting, math.ceil((max(0.0, next_delivery) + round_length) / config().delivery_seconds)))
    return max(1, min(-(-waiting // rounds), waiting - 1))


def checkpoint_tiles(oldest_seconds: float, pending: dict[int, int], state_bytes: dict[int, int]) -> list[int]:
    """The tiles a fold round writes, given the bytes of the deltas each keeps pending and
    its state's bytes: every tile with a delta pending once the oldest pending batch was
    folded checkpoint_seconds ago; else the tiles that free the most bytes per byte written
    (a tile's checkpoint writes its state and drops its deltas) until the deltas left are
    within checkpoint_pending_share of the state's bytes."""
    held = [k for k, p in pending.items() if p > 0]
    if oldest_seconds >= config().checkpoint_seconds:
        return held
    order = sorted(held, key=lambda k: pending[k] / state_bytes[k], reverse=True)
    return _within(order, pending, state_bytes, config().checkpoint_pending_share)


def checkpoint_required(tiles: Sequence[int], pending: dict[int, int], state_bytes: dict[int, int]) -> list[int]:
    """The first of a round's `tiles` (in the order it writes them: checkpoint_tiles) that
    bring the deltas pending within checkpoint_held_share of the state's bytes: the round
    writes these whatever the time, the rest until the next round is due."""
    return _within(tiles, pending, state_bytes, config().checkpoint_held_share)


def _within(tiles: Sequence[int], pending: dict[int, int], state_bytes: dict[int, int], share: float) -> list[int]:
    """The first of `tiles`, in order, whose writes (each drops its pending deltas) bring the
    deltas pending within `share` of the state's bytes."""
    left, cap = sum(pending.values()), share * sum(state_bytes.values())
    out = []
    for k in tiles:
        if left <= cap:
            break
        out.append(k)
        left -= pending.get(k, 0)
    return out


def checkpoint_seconds(next_seconds: float) -> float:
    """How long a regular round may write its tiles after its image: until the next round
    must start (`_start_by`; `next_seconds`: its expected length, round_seconds)."""
    return max(0.0, _start_by(next_seconds))


def seconds_left(settings: Settings, elapsed: float) -> float | None:
    return None if settings.max_seconds is None else max(0.0, settings.max_seconds - elapsed)


def converged(settings: Settings, error: float | None) -> bool:
    """The image's estimated error (after a fold) is at the job's threshold."""
    return settings.error_threshold is not None and error is not None and error <= settings.error_threshold


def after_merge(status: Status, settings: Settings, passes: int, elapsed: float) -> Status:
    """A job's status once a batch is accepted: cancelled if asked, completed when a budget
    is spent, else as it was (convergence is decided where the error is known: the fold)."""
    if status == Status.CANCEL_REQUESTED:
        return Status.CANCELLED
    if passes_left(settings, passes) == 0 or out_of_time(settings, elapsed):
        return Status.COMPLETED
    return status
