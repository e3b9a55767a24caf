"""What another version wrote (worker/store/tiles.py, worker/store/state.py). A delta names
each array's dtype (float32, or float16 scaled by a power of two for the sums a layout
names `half`), and a folder refuses one it cannot read: a batch pushed by a worker of
another version (a float64 delta, or the header of a version that named no dtype) is
accepted by the record, but the fold round writes nothing, the job fails with a message
naming the batch and the dtype, and the batches that were readable fold on the next round
(the failed job's image holds them). The version before float16 (one dtype, float32, for
every array) folds as before. A tile state the previous version wrote as one string (all arrays,
or only the setup arrays before the first fold) reads as the same numbers and folds on.
Real Redis, real store."""

from __future__ import annotations

import json

import numpy as np
import pytest
import redis

from tests.helpers import running_job
from worker.integrators.base import Delta
from worker.settings import Settings
from worker.store import Batch, Jobs, Status, keys
from worker.store.tiles import (
    CACHE,
    DELTA_DTYPE,
    HALF_DTYPE,
    HALF_TOP,
    DeltaFormatError,
    as_sent,
    decode_delta,
    delta_arrays,
    encode_delta,
)

W, H = 32, 16
TILE = 128  # 4 tiles


def _sums(widths: dict[str, int], n: int, seed: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {name: rng.uniform(0.5, 1.5, (n, w) if w > 1 else n) for name, w in widths.items()}


def _running_job(redis_url: str) -> tuple[Jobs, str]:
    """A running job of W x H pixels in TILE-pixel tiles on the test's Redis, its setup written."""
    store = Jobs(redis.Redis.from_url(redis_url), tile_pixels=TILE)
    return store, running_job(store, W, H)


def _foreign(sums: dict[str, np.ndarray], span: slice, header: object, dtype: str) -> bytes:
    """A tile's delta as another version would send it: `header`, then the arrays in `dtype`."""
    head = json.dumps(header).encode()
    head += b" " * (-(len(head) + 1) % 8) + b"\n"
    return head + b"".join(np.ascontiguousarray(a[span], dtype).tobytes() for a in sums.values())


def test_a_delta_names_its_dtypes() -> None:
    sums = {"S": np.ones((4, 3)), "D": np.zeros(4), "X1": np.arange(4.0)}
    payload = bytes(encode_delta(sums, slice(0, 4)))
    assert delta_arrays(payload) == [("S", DELTA_DTYPE, 0), ("X1", DELTA_DTYPE, 0)]  # D is zero: not sent
    header = json.loads(payload[:payload.index(b"\n")])
    assert header["dtypes"] == [DELTA_DTYPE.str] * 2 == ["<f4"] * 2
    np.testing.assert_array_equal(decode_delta(payload, {"S": 3, "D": 1, "X1": 1}, 4)["S"], np.ones((4, 3)))
    with pytest.raises(DeltaFormatError, match="'<f8'"):
        decode_delta(payload.replace(b'"<f4"', b'"<f8"'), {"S": 3, "D": 1, "X1": 1}, 4)
    with pytest.raises(DeltaFormatError, match="does not"):
        decode_delta(payload, {"S": 3, "D": 1}, 4)  # an array this version's state lacks
    # A float16 scale beyond what an encoder writes (2^1028 to read back): refused, not an overflow.
    halves = bytes(encode_delta(sums, slice(0, 4), half=("S",)))
    assert b'"exponents": [0, 14]' in halves
    with pytest.raises(DeltaFormatError, match="scale"):
        decode_delta(halves.replace(b"[0, 14]", b"[0, -916]"), {"S": 3, "D": 1, "X1": 1}, 4)


def test_half_sums_travel_as_scaled_float16_within_its_roundoff() -> None:
    rng = np.random.default_rng(5)
    n = 4096
    # Values over twelve decades in one tile: far below float16's smallest normal (6e-5)
    # and far above its largest (65504) unscaled.
    sums = {"S": rng.gamma(2.0, 1.0, (n, 3)) * 10.0 ** rng.uniform(-6, 6, (n, 1)),
            "D": rng.gamma(2.0, 1.0, n) * 1e-12, "H": np.full(n, 2049.0), "X1": rng.normal(size=n) * 1e9}
    payload = bytes(encode_delta(sums, slice(0, n), half=("S", "D", "H")))
    sent = {name: (dtype, e) for name, dtype, e in delta_arrays(payload)}
    assert sent["X1"] == (DELTA_DTYPE, 0) and {sent[k][0] for k in "SDH"} == {HALF_DTYPE}
    assert list(sent)[0] == "X1"  # float32 first: aligned
    got = decode_delta(payload, {"S": 3, "D": 1, "H": 1, "X1": 1}, n)
    for name in "SDH":
        a, e = sums[name], sent[name][1]
        assert 2.0 ** (HALF_TOP - 1) <= np.max(np.ldexp(a, e)) < 2.0 ** HALF_TOP  # scaled to the top
        # Round to nearest, to float32 and then float16: 2^-24 + 2^-11 (1 + 2^-24), relative;
        # float16's subnormals by their half step, 2^-25, and float32's below them, 2^-38.
        bound = (2.0 ** -11 + 2.0 ** -23) * a + (2.0 ** -25 + 2.0 ** -38) * 2.0 ** -e
        assert np.all(np.abs(got[name] - a) <= bound), name
        # Where float16 is normal, bit for bit numpy's float32-to-float16 cast.
        scaled = np.ldexp(a, e)
        normal = scaled >= 2.0 ** -14
        numpy_cast = np.ldexp(scaled.astype(np.float32).astype(HALF_DTYPE).astype(np.float64), -e)
        np.testing.assert_array_equal(got[name][normal], numpy_cast[normal])
        assert name != "S" or 0 < np.count_nonzero(~normal) < a.size  # both kinds seen
    assert np.all(got["H"] == 2048.0)  # 12 significant bits: float16 keeps 11 (a tie to even)
    np.testing.assert_array_equal(got["X1"], sums["X1"].astype(DELTA_DTYPE))
    # A value that is negative or not finite: the array goes as float32, as it is.
    for bad in (-1e-3, np.inf):
        sums["D"][7] = bad
        dtypes = {name: d for name, d, _ in delta_arrays(bytes(encode_delta(sums, slice(0, n), ("D",))))}
        assert dtypes["D"] == DELTA_DTYPE


@pytest.mark.parametrize("header, dtype, named", [
    ({"dtype": "<f8", "arrays": None}, "<f8", "'<f8'"),  # a version sending float64, its dtype named
    (None, "<f4", "no named dtype"),  # the version before dtypes were named: a bare list of arrays
])
def test_a_delta_of_another_version_fails_its_job_cleanly(redis_url: str, header: object, dtype: str,
                                                           named: str) -> None:
    store, job_id = _running_job(redis_url)
    record = store.get(job_id)
    n, widths, tiling = W * H, dict(record.integrator.sums.widths), store.tiling(record)
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

    assert store.fold(job_id) is None  # the round refused the delta; the job failed
    record = store.get(job_id)
    assert record.status == Status.FAILED
    assert bad.id in record.failure and named in record.failure, record.failure
    assert not store.r.hexists(keys.tofold(job_id), bad.id)  # never folded, never retried
    for k in range(tiling.count):  # nothing of it on a tile
        assert bad.id.encode() not in store.r.smembers(keys.tile(job_id, k, "folded"))
    # The readable batches fold: the failed job's image holds them.
    state = store.state(record)
    assert record.folded_passes == state.passes == 4 and not store.r.exists(keys.tofold(job_id))
    assert store.published(record).passes == 4
    expected = sum(as_sent(d.sums, tiling, record.integrator.sums.half)["S"] for d in good)
    np.testing.assert_allclose(state.S, expected, rtol=1e-12)


def test_a_delta_of_the_version_before_float16_folds(redis_url: str) -> None:
    """One dtype named for every array, float32: a job that a rolling upgrade catches
    between its batches folds them all."""
    store, job_id = _running_job(redis_url)
    record = store.get(job_id)
    n, widths, tiling = W * H, dict(record.integrator.sums.widths), store.tiling(record)
    new, old = Delta(0, 2, 4096, _sums(widths, n, 1)), Batch(job_id, 2, 2)
    assert store.merge(Batch(job_id, 0, 2), new, 0.01) == "merged"
    sums = _sums(widths, n, 2)
    head = {"dtype": "<f4", "arrays": list(sums)}
    store.tiles.push_encoded(job_id, tiling, old.id, lambda k: _foreign(sums, tiling.span(k), head, "<f4"))
    assert store.accept(old, Delta(2, 2, 4096, {}), 0.01, 0.01)[0] == "merged"
    assert store.fold(job_id, checkpoint=True) is not None
    record = store.get(job_id)
    assert record.status == Status.RUNNING and record.folded_passes == 4
    expected = as_sent(new.sums, tiling, record.integrator.sums.half)["S"] + sums["S"].astype(np.float32)
    np.testing.assert_allclose(store.state(record).S, expected, rtol=1e-12)


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
