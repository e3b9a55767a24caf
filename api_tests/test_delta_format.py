"""What another version wrote (worker/store/tiles.py, worker/store/state.py). A delta names
its dtype, and a folder refuses one it cannot read: a batch pushed by a worker of another
version (a float64 delta, or the header of a version that named no dtype) is accepted by
the record, but the fold round writes nothing, the job fails with a message naming the
batch and the dtype, and the batches that were readable fold on the next round (the failed
job's image holds them). A tile state the previous version wrote as one string (all arrays,
or only the setup arrays before the first fold) reads as the same numbers and folds on.
Real Redis, real store."""

from __future__ import annotations

import json

import numpy as np
import pytest
import redis

from worker.integrators.base import Delta
from worker.settings import Settings
from worker.store import Batch, Jobs, Status, keys
from worker.store.tiles import CACHE, DELTA_DTYPE, DeltaFormatError, decode_delta, delta_arrays, encode_delta

W, H = 32, 16
TILE = 128  # 4 tiles


def _sums(widths: dict[str, int], n: int, seed: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {name: rng.uniform(0.5, 1.5, (n, w) if w > 1 else n) for name, w in widths.items()}


def _foreign(sums: dict[str, np.ndarray], span: slice, header: object, dtype: str) -> bytes:
    """A tile's delta as another version would send it: `header`, then the arrays in `dtype`."""
    head = json.dumps(header).encode()
    head += b" " * (-(len(head) + 1) % 8) + b"\n"
    return head + b"".join(np.ascontiguousarray(a[span], dtype).tobytes() for a in sums.values())


def test_a_delta_names_its_dtype() -> None:
    sums = {"S": np.ones((4, 3)), "D": np.zeros(4)}
    payload = bytes(encode_delta(sums, slice(0, 4)))
    assert delta_arrays(payload) == ["S"]  # D is zero over the tile: not sent
    assert json.loads(payload[:payload.index(b"\n")])["dtype"] == DELTA_DTYPE.str == "<f4"
    np.testing.assert_array_equal(decode_delta(payload, {"S": 3, "D": 1}, 4)["S"], np.ones((4, 3)))
    with pytest.raises(DeltaFormatError, match="'<f8'"):
        decode_delta(payload.replace(b'"<f4"', b'"<f8"'), {"S": 3, "D": 1}, 4)
    with pytest.raises(DeltaFormatError, match="does not"):
        decode_delta(payload, {"D": 1}, 4)  # an array this version's state lacks


@pytest.mark.parametrize("header, dtype, named", [
    ({"dtype": "<f8", "arrays": None}, "<f8", "'<f8'"),  # a version sending float64, its dtype named
    (None, "<f4", "no named dtype"),  # the version before dtypes were named: a bare list of arrays
])
def test_a_delta_of_another_version_fails_its_job_cleanly(redis_url: str, header: object, dtype: str,
                                                           named: str) -> None:
    store = Jobs(redis.Redis.from_url(redis_url), tile_pixels=TILE)
    job_id = store.create({}, Settings(max_passes=1000), W, H, None)
    record = store.get(job_id)
    n, widths = W * H, dict(record.integrator.sums.widths)
    store.init_setup(record, {"R0": np.full(n, 0.05)})
    store.r.hset(keys.job(job_id), mapping={"status": "running", "started": 1.0})
    tiling = store.tiling(record)
    good = [Delta(2 * b, 2, 4096, _sums(widths, n, b)) for b in range(2)]
    for d in good:
        assert store.merge(Batch(job_id, d.first_pass, 2), d, 0.01) == "merged"
    # A worker of another version pushes batch 4..5 and has it accepted.
    bad = Batch(job_id, 4, 2)
    sums = _sums(widths, n, 9)
    names = list(sums)
    head = {**header, "arrays": names} if isinstance(header, dict) else names
    store.tiles.push_encoded(job_id, tiling, bad.id, lambda k: _foreign(sums, tiling.span(k), head, dtype))
    assert store.accept(bad, Delta(4, 2, 4096, {}), 0.01, 0.01)[0] == "merged"

    assert store.fold(job_id) is None  # the round refused the delta and wrote nothing
    record = store.get(job_id)
    assert record.status == Status.FAILED
    assert bad.id in record.failure and named in record.failure, record.failure
    assert record.folded_passes == 0
    for k in range(tiling.count):
        assert not store.r.hget(keys.tile(job_id, k, "meta"), "version")
    assert not store.r.hexists(keys.tofold(job_id), bad.id)  # never folded, never retried
    # The readable batches fold: the failed job's image holds them.
    state = store.state(record)
    record = store.get(job_id)
    assert record.folded_passes == state.passes == 4 and not store.r.exists(keys.tofold(job_id))
    expected = sum(d.sums["S"].astype(DELTA_DTYPE).astype(np.float64) for d in good)
    np.testing.assert_allclose(state.S, expected, rtol=1e-12)


def test_a_tile_state_of_the_previous_version_reads_and_folds_on(redis_url: str) -> None:
    store = Jobs(redis.Redis.from_url(redis_url), tile_pixels=TILE)
    jobs = [store.create({}, Settings(max_passes=1000), W, H, None) for _ in range(2)]
    n = W * H
    record = store.get(jobs[0])
    widths, tiling = record.integrator.state_widths, store.tiling(record)
    deltas = [Delta(2 * b, 2, 4096, _sums(dict(record.integrator.sums.widths), n, b)) for b in range(2)]
    for job_id in jobs:
        store.init_setup(store.get(job_id), {"R0": np.full(n, 0.05)})
        store.r.hset(keys.job(job_id), mapping={"status": "running", "started": 1.0})
        assert store.merge(Batch(job_id, 0, 2), deltas[0], 0.01) == "merged"
        assert store.fold(job_id, checkpoint=True) is not None
    # Job 1's tiles as the previous version stored them: every array in the state's order
    # in one string; tile 0 as before its first fold (only R0).
    legacy = store.state(store.get(jobs[1])).arrays()
    for k in range(tiling.count):
        span = tiling.span(k)
        names = ["R0"] if k == 0 else list(widths)
        store.r.delete(keys.tile(jobs[1], k, "state"))
        store.r.set(keys.tile(jobs[1], k, "state"), b"".join(legacy[name][span].tobytes() for name in names))
    CACHE._items.clear()
    CACHE._bytes = 0
    got = store.state(store.get(jobs[1])).arrays()
    for name in widths:
        expected = legacy[name].copy()
        expected[tiling.span(0)] = legacy[name][tiling.span(0)] if name == "R0" else 0.0
        np.testing.assert_array_equal(got[name], expected, err_msg=name)
    assert store.r.type(keys.tile(jobs[1], 0, "state")) == b"hash"
    # Tiles 1.. fold on as the job that never had the old layout.
    for job_id in jobs:
        assert store.merge(Batch(job_id, 2, 2), deltas[1], 0.01) == "merged"
        assert store.fold(job_id, checkpoint=True) is not None
    states = [store.state(store.get(job_id)).arrays() for job_id in jobs]
    rest = slice(tiling.span(1).start, n)
    for name in widths:
        np.testing.assert_array_equal(states[1][name][rest], states[0][name][rest], err_msg=name)
