"""The job state's storage over a long run: 10^4 passes (1000 batches of 10) pushed,
accepted and folded through the tiles of a real Redis, against the same sums kept in
extended precision. With the float64 storage the folded sums, the per-pixel variance
(X2 - X1^2 / n, the estimator's cancellation) and the image stay within 1e-12 of the
reference; float32 storage of the same stream drifts by more than 1e-6 (checked here,
so the test could tell)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import redis

from service.redis_server import EmbeddedRedis
from worker.integrators.base import Delta
from worker.settings import Settings
from worker.store import Batch, Jobs, keys

W, H = 32, 16
BATCHES, PASSES = 1000, 10  # 10^4 passes
FOLD_EVERY = 5  # batches accepted between folds
SIGNED = {"G", "X1", "Dh"}


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


def test_ten_thousand_passes_show_no_drift_in_float64_storage(tmp_path: Path) -> None:
    server = EmbeddedRedis(tmp_path / "redis").start(supervise=False)
    try:
        store = Jobs(redis.Redis.from_url(server.url), tile_pixels=128)  # 4 tiles
        job_id = store.create({}, Settings(max_passes=BATCHES * PASSES), W, H, None)
        record = store.get(job_id)
        n = W * H
        store.init_setup(record, {"R0": np.full(n, 0.05)})
        store.r.hset(keys.job(job_id), mapping={"status": "running", "started": 1.0})
        widths = dict(record.integrator.sums.widths)
        rng = np.random.default_rng(7)
        scale = 10.0 ** rng.uniform(-3, 3, n)
        reference = {name: np.zeros((n, w) if w > 1 else n, np.longdouble) for name, w in widths.items()}
        single = {name: np.zeros_like(ref, np.float32) for name, ref in reference.items()}
        emitted = 1 << 12
        for b in range(BATCHES):
            batch_sums = {name: np.zeros_like(ref, np.float64) for name, ref in reference.items()}
            for _ in range(PASSES):  # the device sums a batch's passes in float64
                for name, value in _pass_sums(rng, widths, scale).items():
                    batch_sums[name] += value
                    reference[name] += value.astype(np.longdouble)
            for name, value in batch_sums.items():
                single[name] += value.astype(np.float32)
            delta = Delta(b * PASSES, PASSES, PASSES * emitted, batch_sums)
            assert store.merge(Batch(job_id, b * PASSES, PASSES), delta, 0.01) == "merged"
            if b % FOLD_EVERY == FOLD_EVERY - 1 and b < BATCHES - 1:  # the last batch ends the job: it folds
                assert store.fold(job_id) is not None
        state = store.state(store.get(job_id))
        assert state.passes == BATCHES * PASSES and state.emitted == BATCHES * PASSES * emitted

        def drift(got: np.ndarray, ref: np.ndarray) -> float:
            return float(np.max(np.abs(got.astype(np.longdouble) - ref) / np.abs(ref)))

        for name in widths:
            assert drift(getattr(state, name), reference[name]) < 1e-12, name
        worst32 = max(drift(single[name], reference[name]) for name in widths)
        assert worst32 > 1e-6, worst32  # float32 storage would drift: the test can see it
        # The variance of the per-pass samples: X2 - X1^2/n cancels to 1e-3 of X2.
        m = BATCHES * PASSES

        def variance(x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
            x1, x2 = x1.astype(np.longdouble), x2.astype(np.longdouble)
            return (x2 - x1 * x1 / m) / (m - 1)

        ref_var = variance(reference["X1"], reference["X2"])
        assert drift(variance(state.X1, state.X2), ref_var) < 1e-9
        assert drift(variance(single["X1"], single["X2"]), ref_var) > 1e-4
        # The image.
        ref_image = reference["S"] / (m * emitted) + reference["Ld"] / m
        assert drift(record.integrator.image(state), ref_image) < 1e-12
    finally:
        server.stop()
