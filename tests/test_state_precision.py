"""The job state's storage over a long run: 10^4 passes (1000 batches of 10) pushed,
accepted and folded through the tiles of a real Redis, against the same sums kept in
extended precision. A batch's delta is sent as float32, the photon sums (SumLayout.half)
as float16 scaled per tile by a power of two (worker/store/tiles.py), and folded into
float64 sums, so:
- the folded sums are the sums of the deltas as sent, within 1e-12 (the fold adds exactly);
- against the exact sums of the passes, every folded sum is off by at most its dtype's unit
  roundoff (2^-24 for float32, 2^-11 + 2^-23 for float16) of the sum of its batches'
  magnitudes (each batch rounded once; float16 also by its subnormals' step, 2^-39 of a
  batch's largest value), after 10^4 passes as after one: no drift. float32 *storage* of
  the same stream drifts more than 16 times the float32 bound (checked here, so the test
  could tell the two apart);
- the image (sums of non-negative terms) is within float16's roundoff, relative (and that
  step); the per-pixel variance (X2 - X1^2 / n, which cancels to 1e-3 of X2; float32 sums)
  stays within its first-order rounding bound, far below the variance estimate's own
  statistical error (sqrt(2 / (n - 1)) = 1.4%)."""

from __future__ import annotations

import numpy as np
import redis

from tests.helpers import running_job
from worker.integrators.base import Delta
from worker.settings import Settings
from worker.store import Batch, Jobs
from worker.store.tiles import as_sent

W, H = 32, 16
BATCHES, PASSES = 1000, 10  # 10^4 passes
FOLD_EVERY = 5  # batches accepted between folds
SIGNED = {"G", "GR", "X1", "Dh"}
UNIT = 2.0 ** -24  # float32's unit roundoff (round to nearest) ...
HALF_UNIT = 2.0 ** -11 + 2.0 ** -23  # ... float16's, after float32's (two roundings) ...
HALF_STEP = 2.0 ** -39 * (1 + 2.0 ** -13)  # ... and its subnormals' half step (and float32's), of the tile's largest


def _pass_sums(rng: np.random.Generator, widths: dict[str, int], scale: np.ndarray) -> dict[str, np.ndarray]:
    """One pass's per-pixel sums: magnitudes spread over six decades across pixels; the
    bias-corrected sample X1 a mean plus 3% noise, X2 its square."""
    out = {}
    for name, width in widths.items():
        shape = (len(scale), width) if width > 1 else (len(scale),)
        s = scale.reshape(-1, 1) if width > 1 else scale
        out[name] = s * (rng.normal(0.0, 1.0, shape) if name in SIGNED else rng.gamma(2.0, 1.0, shape))
    out["X1"] = scale * (1.0 + 0.03 * rng.normal(size=len(scale)))
    out["X2"] = out["X1"] ** 2
    out["H"] = np.ones(len(scale))
    return out


def test_ten_thousand_passes_show_no_drift_with_float32_and_float16_deltas(redis_url: str) -> None:
    store = Jobs(redis.Redis.from_url(redis_url), tile_pixels=128)  # 4 tiles
    job_id = running_job(store, W, H, settings=Settings(max_passes=BATCHES * PASSES))
    record = store.get(job_id)
    n = W * H
    widths, half, tiling = dict(record.integrator.sums.widths), record.integrator.sums.half, store.tiling(record)
    assert {"S", "Ld"} <= set(half) and not {"X1", "X2"} & set(half)
    unit = {name: HALF_UNIT if name in half else UNIT for name in widths}
    rng = np.random.default_rng(7)
    scale = 10.0 ** rng.uniform(-3, 3, n)

    def zeros(dtype: type) -> dict[str, np.ndarray]:
        return {name: np.zeros((n, w) if w > 1 else n, dtype) for name, w in widths.items()}

    # Extended precision: the exact sums of the passes, of the deltas as sent, and of the
    # batches' magnitudes; and float32 storage of the running sums, for contrast.
    exact, sent, magnitude, single = zeros(np.longdouble), zeros(np.longdouble), zeros(np.longdouble), \
        zeros(np.float32)
    step = dict.fromkeys(widths, 0.0)  # float16's subnormal steps, summed over the batches
    emitted = 1 << 12
    for b in range(BATCHES):
        batch_sums = zeros(np.float64)
        for _ in range(PASSES):  # the device sums a batch's passes in float64
            for name, value in _pass_sums(rng, widths, scale).items():
                batch_sums[name] += value
                exact[name] += value.astype(np.longdouble)
        for name, value in as_sent(batch_sums, tiling, half).items():
            sent[name] += value.astype(np.longdouble)
        for name, value in batch_sums.items():
            magnitude[name] += np.abs(value).astype(np.longdouble)
            step[name] += HALF_STEP * float(np.abs(value).max()) if name in half else 0.0
            single[name] += value.astype(np.float32)
        delta = Delta(b * PASSES, PASSES, PASSES * emitted, batch_sums)
        assert store.merge(Batch(job_id, b * PASSES, PASSES), delta, 0.01) == "merged"
        if b % FOLD_EVERY == FOLD_EVERY - 1 and b < BATCHES - 1:  # the last batch ends the job: it folds
            assert store.fold(job_id) is not None
    state = store.state(store.get(job_id))
    assert state.passes == BATCHES * PASSES and state.emitted == BATCHES * PASSES * emitted

    def error(got: np.ndarray, ref: np.ndarray, name: str) -> float:
        """The largest error over pixels, in units of the sum of the batches' magnitudes."""
        return float(np.max(np.abs(got.astype(np.longdouble) - ref) / magnitude[name]))

    for name in state.sums:  # (a batch's M goes into N, not kept: worker/stats.py)
        got = getattr(state, name)
        assert error(got, sent[name], name) < 1e-12, name  # the fold adds exactly
        off = np.abs(got.astype(np.longdouble) - exact[name])  # one rounding a batch:
        assert np.all(off <= unit[name] * (1 + 1e-6) * magnitude[name] + step[name]), name
    assert error(state.S, exact["S"], "S") > 16 * UNIT  # the photon sums went as float16: the test sees it
    worst32 = max(error(single[name], exact[name], name) for name in state.sums)
    assert worst32 > 16 * UNIT, worst32  # float32 storage drifts: the test can see it
    # The variance of the per-pass samples: X2 - X1^2/m cancels to 1e-3 of X2. Its
    # first-order rounding bound: u (|X2| + 2 |X1| |X1| / m) / (m - 1), with |.| the
    # batches' magnitudes.
    m = BATCHES * PASSES

    def variance(x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
        x1, x2 = x1.astype(np.longdouble), x2.astype(np.longdouble)
        return (x2 - x1 * x1 / m) / (m - 1)

    ref_var = variance(exact["X1"], exact["X2"])
    bound = UNIT * (magnitude["X2"] + 2 * np.abs(exact["X1"]) * magnitude["X1"] / m) / (m - 1)
    var_error = np.abs(variance(state.X1, state.X2) - ref_var)
    assert np.all(var_error <= 1.01 * bound)
    assert float(np.max(var_error / ref_var)) < 1e-3 * np.sqrt(2.0 / (m - 1))
    assert float(np.max(np.abs(variance(single["X1"], single["X2"]) - ref_var) / ref_var)) > 1e-4
    # The image: non-negative float16 sums, so within float16's unit roundoff, relative (and
    # the subnormals' step).
    ref_image = exact["S"] / (m * emitted) + exact["Ld"] / m
    image = record.integrator.image(state).astype(np.longdouble)
    floor = step["S"] / (m * emitted) + step["Ld"] / m
    assert np.all(np.abs(image - ref_image) <= HALF_UNIT * (1 + 1e-6) * ref_image + floor)
