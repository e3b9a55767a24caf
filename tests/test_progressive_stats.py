"""The update rule and the merge, on deltas produced by the real kernels."""

from __future__ import annotations

import dataclasses
import json
import math
from itertools import pairwise
from pathlib import Path

import numpy as np
import pytest

import worker.integrators.photon_mapping_passes as photon_mapping_passes
from worker import stats
from worker.integrators.base import Delta
from worker.integrators.photon_mapping import GatherInputs, sum_layout
from worker.render_loop import render as render_passes
from worker.scene import bundled_scene_path
from worker.stats import Accumulators

LAYOUT = sum_layout(error_estimation=True)


def test_first_pass_identities(make_engine) -> None:
    """With N0 = 0: R1^2 = alpha R0^2 exactly and N1 = alpha M1 (digest 3.8, T3)."""
    alpha = 0.7
    eng = make_engine("furnace", photons_per_pass=1 << 15, seed=11, alpha=alpha)
    state = eng.start()
    r0 = state.radius()
    delta = eng.run_batch(GatherInputs(r0), 0, 1)
    state.merge(delta)
    lit = delta.D > 0
    assert lit.mean() > 0.5  # most pixels found photons: the identity is checked on them
    r0_device = r0.astype(np.float32).astype(np.float64)  # the radius the pass gathered at
    np.testing.assert_allclose(state.radius()[lit] ** 2, alpha * r0_device[lit] ** 2, rtol=1e-12)
    m1 = delta.D * math.pi * r0_device ** 2  # photons found in pass 1
    np.testing.assert_allclose(state.N[lit], alpha * m1[lit], rtol=1e-6)
    np.testing.assert_allclose(m1[lit], np.round(m1[lit]), atol=1e-3)  # M is a photon count


def test_second_pass_is_the_sequential_ppm_update(make_engine) -> None:
    """D-form merge of a pass gathered at the current radius = eq. 6.5/6.6."""
    alpha = 0.7
    eng = make_engine("furnace", photons_per_pass=1 << 15, seed=12, alpha=alpha)
    state = eng.start()
    state.merge(eng.run_batch(GatherInputs(state.radius()), 0, 1))
    r1, n1 = state.radius(), state.N.copy()
    r1_used = r1.astype(np.float32).astype(np.float64)
    delta = eng.run_batch(GatherInputs(r1), 1, 1)
    state.merge(delta)
    m2 = delta.D * math.pi * r1_used ** 2
    lit = (n1 > 0) & (m2 > 0)
    expected_r2 = r1[lit] ** 2 * (n1[lit] + alpha * m2[lit]) / (n1[lit] + m2[lit])
    np.testing.assert_allclose(state.radius()[lit] ** 2, expected_r2, rtol=1e-6)


def test_D_is_additive_and_merge_order_does_not_change_the_estimate(make_engine) -> None:
    """S, D, E and Ld are sums: any merge order gives the same image (to rounding)."""
    eng = make_engine("cornell-caustics", resolution=(48, 48), photons_per_pass=1 << 15, seed=13)
    r0 = eng.start().R0
    # Batches gathered at different (stale) radii, as concurrent workers would.
    deltas = [eng.run_batch(GatherInputs(r0 * s), 2 * i, 2) for i, s in enumerate((1.0, 0.8, 1.0, 0.6, 0.9))]
    orders = [[0, 1, 2, 3, 4], [4, 2, 0, 3, 1], [3, 4, 1, 0, 2]]
    states = []
    for order in orders:
        st = Accumulators.start(0.7, r0, LAYOUT)
        for i in order:
            st.merge(deltas[i])
        states.append(st)
    np.testing.assert_array_equal(states[0].emitted, states[1].emitted)
    for st in states[1:]:
        for name in LAYOUT.names:  # rounding of a reordered sum scales with its largest term
            ref = states[0].sums[name]
            np.testing.assert_allclose(st.sums[name], ref, rtol=1e-12, atol=1e-12 * np.abs(ref).max())
        np.testing.assert_allclose(st.radiance(), states[0].radiance(), rtol=1e-13, atol=1e-300)
    np.testing.assert_allclose(states[0].D, sum(d.D for d in deltas), rtol=1e-13)
    # N (the future radius schedule) depends on the order pixel by pixel, through photon
    # noise, but not in aggregate: the mean R^2 over lit pixels agrees to a few percent.
    lit = states[0].D > 0
    mean_r2 = [np.mean(st.radius()[lit] ** 2) for st in states]
    assert max(mean_r2) / min(mean_r2) < 1.03, mean_r2


@pytest.mark.parametrize("scene, method", [("cornell-box", "sppm"), ("gap", "sppm"), ("cornell-box", "vcm")])
def test_the_initial_radius_from_a_subset_of_pixels_is_the_whole_frames(make_engine, monkeypatch, scene: str,
                                                                         method: str) -> None:
    """R0's medians (eye-path length; photon density at the probe, SPPM) taken at every 5th
    pixel (PROBE_POINTS, the set-up's cost at large frames) land within 2% of the whole
    frame's: the probe gathers at the subset's own measurement points."""
    settings = dict(resolution=(160, 120), photons_per_pass=1 << 14, seed=3, method=method)
    r0 = {}
    for points in (1 << 12, 1 << 30):  # a stride of 5, then every pixel
        monkeypatch.setattr(photon_mapping_passes, "PROBE_POINTS", points)
        r0[points] = make_engine(scene, **settings).passes.setup()["R0"]
    assert np.ptp(r0[1 << 12]) == 0.0
    assert r0[1 << 12][0] == pytest.approx(r0[1 << 30][0], rel=0.02)


def test_the_initial_radius_does_not_depend_on_the_frame_size(make_engine) -> None:
    """R0 by the photon rule is a distance in the scene. At 1920x1080 gap's probe (8 pixel
    footprints) caught a photon or two where it caught any, overstating the density by the
    photons it missed: R0 was 27% below 256x256's (43% at 3840x2160). The probe now grows
    until its median lit point holds PROBE_MIN_PHOTONS. (The same photons a pass at both sizes:
    by default they follow the pixel count, and R0 with them.)"""
    r0 = [make_engine("gap", resolution=size, seed=3, photons_per_pass=1 << 18).passes.setup()["R0"][0]
          for size in ((256, 256), (1920, 1080))]
    assert r0[1] == pytest.approx(r0[0], rel=0.1)


def test_a_close_up_gets_a_radius_its_photons_reach(make_engine, tmp_path: Path) -> None:
    """cornell-box at fov 0.01: the probe caught no photon at all, R0 fell to 2 pixel
    footprints (0.015), which no photon ever reached, and the image stayed black."""
    scene = json.loads(bundled_scene_path("cornell-box").read_text())
    scene["camera"]["fov"] = 0.01
    path = tmp_path / "close-up.json"
    path.write_text(json.dumps(scene))
    wide = make_engine("cornell-box", seed=3, photons_per_pass=1 << 16).passes.setup()["R0"][0]
    engine = make_engine(path, resolution=(16, 16), seed=3, photons_per_pass=1 << 16)
    state = render_passes(engine, passes=4)
    assert state.R0[0] > 0.3 * wide  # the back wall's photon density, seen through a pinhole
    assert np.all(engine.integrator.image(state) > 0.0)


def test_unlit_pixels_keep_a_bounded_radius() -> None:
    """A pixel that never found a photon has no statistics: R0, capped at the largest lit radius."""
    st = Accumulators.start(0.5, np.full(3, 2.0), LAYOUT)
    zero = np.zeros(3)
    sums = {name: LAYOUT.zeros(3, name) for name in LAYOUT.names}
    sums["D"] = np.array([1.0, 0.0, 0.0])
    sums["M"] = math.pi * 2.0 ** 2 * sums["D"]  # the photons found at R0 = 2
    st.merge(Delta(0, 1, 10, sums=sums))
    r = st.radius()
    assert r[0] == np.sqrt(0.5) * 2.0  # R1^2 = alpha R0^2
    assert r[1] == r[2] == r[0]
    assert np.array_equal(st.D[1:], zero[1:])


@pytest.mark.parametrize("alpha", [0.3, 2.0 / 3.0, 1.0])
def test_the_schedule_a_state_holds(alpha: float) -> None:
    """The SCHEDULE counter sums a_k = prod_{i<k} (i + alpha) / (i + 1) (eq. 6.6 under a
    uniform density) over a batch's passes, by the closed form A(K) = Gamma(K + alpha) /
    (Gamma(1 + alpha) Gamma(K)); a state holding the passes 0 .. K-1 in any batches is a
    prefix (scale exactly 1), one holding pass 1 alone is 1 / alpha below one pass, and one
    missing its earliest passes below the prefix by the schedule's sums."""
    total = 10 ** 6
    a = np.cumprod(np.r_[1.0, (np.arange(total - 1) + alpha) / (np.arange(total - 1) + 1)])
    cuts = np.unique(np.r_[0, np.random.default_rng(3).integers(1, total, 3000), total - 3, total - 1, total])
    counts = [stats.schedule_count(alpha, int(lo), int(hi - lo)) for lo, hi in pairwise(cuts)]
    A = np.cumsum(a)
    for (lo, hi), count in zip(pairwise(cuts), counts, strict=True):
        # to the quantum and 1e-13 of A (the reference's own)
        assert abs(count * stats.SCHEDULE_QUANTUM - a[lo:hi].sum()) <= stats.SCHEDULE_QUANTUM + 1e-13 * A[hi - 1]
    assert stats.prefix_scale(alpha, total, {stats.SCHEDULE: sum(counts)}) == 1.0
    a = a[:5000]
    assert stats.prefix_scale(alpha, 5000, {}) == 1.0  # a state of no counter (before it)
    assert stats.schedule_count(alpha, 0, 10_000_000) < 2 ** 50  # exact as a double (the record's Lua)
    one = {stats.SCHEDULE: stats.schedule_count(alpha, 1, 1)}
    assert stats.prefix_scale(alpha, 1, one) == pytest.approx(1.0 / alpha, rel=1e-7)  # to the quantum
    late = {stats.SCHEDULE: stats.schedule_count(alpha, 100, 400)}  # passes 100 .. 499, not 0 .. 99
    assert stats.prefix_scale(alpha, 400, late) == pytest.approx(a[:400].sum() / a[100:500].sum(), rel=1e-7)


@pytest.mark.parametrize("alpha", [0.5, 0.7])
def test_a_pass_before_the_passes_its_inputs_hold_gathers_where_the_job_would(make_engine, alpha: float) -> None:
    """A job's first round holds pass 1 alone, and pass 0 starts from it (its worker was late):
    pass 0 gathers at R0 with N = 0 (stats.rewind), so the state of passes 0 and 1 has the
    sequential radius (median over lit pixels within 2%). Without the rewind pass 0 gathers
    at pass 1's radius and the state ends about 9% small."""
    eng = make_engine("furnace", photons_per_pass=1 << 13, seed=4, alpha=alpha)
    sequential = eng.start()
    for k in range(2):
        sequential.merge(eng.run_batch(eng.integrator.batch_inputs(sequential), k, 1))
    lit = sequential.D > 0

    def late_pass_zero(rewound: bool) -> Accumulators:
        state = eng.start()
        state.merge(eng.run_batch(dataclasses.replace(eng.integrator.batch_inputs(state), passes=0), 1, 1))
        inputs = eng.integrator.batch_inputs(state)  # holds pass 1
        state.merge(eng.run_batch(inputs if rewound else dataclasses.replace(inputs, passes=0), 0, 1))
        return state

    ratio = np.median(late_pass_zero(True).radius()[lit] / sequential.radius()[lit])
    assert abs(ratio - 1.0) < 0.02, ratio
    assert np.median(late_pass_zero(False).radius()[lit] / sequential.radius()[lit]) < 0.95


@pytest.mark.parametrize("alpha", [0.3, 0.7, 1.0])
def test_rewind_follows_the_schedule_back(alpha: float) -> None:
    """rewind's factors are the uniform-density schedule's: R_k^2 / R_P^2 = a_k / a_P and
    N_k / N_P = A(k) / A(P), with pass 0 at N = 0."""
    a = np.cumprod(np.r_[1.0, (np.arange(99) + alpha) / (np.arange(99) + 1)])
    A = np.r_[0.0, np.cumsum(a)]
    for first, passes in [(0, 1), (0, 7), (3, 10), (40, 41), (1, 99), (9, 9)]:
        n_factor, r2_factor = stats.rewind(alpha, passes, first)
        if first == passes:
            assert (n_factor, r2_factor) == (1.0, 1.0)
            continue
        assert n_factor == pytest.approx(A[first] / A[passes], rel=1e-12, abs=0.0)
        assert r2_factor == pytest.approx(a[first] / a[passes], rel=1e-12)


def test_a_batch_moves_its_radius_on_as_sequential_passes_do(make_engine) -> None:
    """A batch of several passes gathers each pass at the radius the sequential update
    would give (shrink_radius on the device), so folding it lands N and R where merging its
    passes one by one does: the radius schedule does not depend on the batch length.
    (Uniform photons: chain passes take their mutation size from the batch's start, so a
    batch's chains are not one-by-one passes' chains.)"""
    eng = make_engine("cornell-caustics", resolution=(48, 48), photons_per_pass=1 << 14, seed=14, sampler="uniform")
    one_by_one = eng.start()
    for k in range(6):
        one_by_one.merge(eng.run_batch(eng.integrator.batch_inputs(one_by_one), k, 1))
    batched = eng.start()
    batched.merge(eng.run_batch(eng.integrator.batch_inputs(batched), 0, 3))
    batched.merge(eng.run_batch(eng.integrator.batch_inputs(batched), 3, 3))
    # Pixels with photons from the first pass on follow the rule alone, in float32 on the
    # device and float64 on the host. (One first lit later keeps its radius within a batch,
    # where the host caps an unlit pixel's radius at the largest lit one after each merge:
    # a free choice for a pixel with no statistics, stats.radius.)
    lit = eng.run_batch(eng.integrator.batch_inputs(eng.start()), 0, 1).D > 0
    assert lit.mean() > 0.5
    np.testing.assert_allclose(batched.radius()[lit], one_by_one.radius()[lit], rtol=1e-5)
    np.testing.assert_allclose(batched.N[lit], one_by_one.N[lit], rtol=1e-5)
    np.testing.assert_allclose(batched.radiance().mean(axis=0), one_by_one.radiance().mean(axis=0), rtol=1e-3)


@pytest.mark.parametrize("lacking, after_a_pass", [(0, True), (2, True), (40, True), (300, True), (40, False),
                                                    (300, False)])
def test_a_batch_takes_the_rule_for_the_passes_its_inputs_lack(make_engine, lacking: int,
                                                               after_a_pass: bool) -> None:
    """A batch whose first pass is the job's k-th while its inputs hold fewer passes takes
    the radius rule once for each pass they lack and once for itself, each step with the
    photons it found scaled to the step's disc, M (R_j / R)^2: the host's float64 recursion
    gives the device's count and radius, and the radius keeps the rule's invariant
    R^2 = N / (pi (D + W dD)), W the steps. The photons the pass adds to N (sum M) are
    those of its own step, the last. Past 16 steps the device takes them in closed form;
    also from a job's first pass (N = 0)."""
    import pyopencl as cl

    alpha = 0.7
    eng = make_engine("cornell-caustics", resolution=(48, 48), photons_per_pass=1 << 14, seed=15, alpha=alpha)
    state = eng.start()
    if after_a_pass:
        state.merge(eng.run_batch(eng.integrator.batch_inputs(state), 0, 1))
    inputs = eng.integrator.batch_inputs(state)
    assert inputs.passes == state.passes
    delta = eng.run_batch(inputs, state.passes + lacking, 1)
    n = eng.arrays.n_pixels
    radius, count = np.empty(n, np.float32), np.empty(n, np.float32)
    cl.enqueue_copy(eng.device.queue, radius, eng.passes.radius)
    cl.enqueue_copy(eng.device.queue, count, eng.passes.radius_count)
    rb = inputs.radius.astype(np.float32).astype(np.float64)
    lit = delta.D > 0
    assert lit.mean() > 0.5
    rb, m = rb[lit], (math.pi * rb ** 2 * delta.D)[lit]  # the photons the pass found, at its radius rb
    expected, r2 = inputs.count.astype(np.float32).astype(np.float64)[lit], np.ones(len(m))
    for j in range(lacking + 1):
        mj = m * r2
        if j == lacking:
            np.testing.assert_allclose(delta.sums["M"][lit], mj, rtol=1e-5)
        r2 *= (expected + alpha * mj) / (expected + mj)
        expected = expected + alpha * mj
    np.testing.assert_allclose(count[lit], expected, rtol=1e-5)
    np.testing.assert_allclose(radius[lit].astype(np.float64) ** 2, rb ** 2 * r2, rtol=1e-5)
    np.testing.assert_allclose(radius[lit].astype(np.float64) ** 2,
                               expected / (math.pi * (state.D[lit] + (lacking + 1) * delta.D[lit])), rtol=1e-4)


def test_a_batch_catches_up_at_its_first_pass_only(make_engine) -> None:
    """A batch whose inputs lack 5 of the passes before it: a 3-pass batch ends where a
    1-pass batch and then a 2-pass batch from its radius, count and bias end (float32 on
    the device), and without the catch-up the radius ends larger."""
    import pyopencl as cl

    eng = make_engine("cornell-caustics", resolution=(48, 48), photons_per_pass=1 << 14, seed=16, alpha=0.7)
    state = eng.start()
    state.merge(eng.run_batch(eng.integrator.batch_inputs(state), 0, 1))
    start = eng.integrator.batch_inputs(state)
    n = eng.arrays.n_pixels

    def device() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        out = [np.empty(n, np.float32) for _ in range(3)]
        for host, buf in zip(out, (eng.passes.radius, eng.passes.radius_count, eng.passes.bias), strict=True):
            cl.enqueue_copy(eng.device.queue, host, buf)
        return tuple(out)

    whole = eng.run_batch(start, 6, 3)
    whole_end = device()
    first = eng.run_batch(start, 6, 1)
    radius, count, bias = device()
    rest = eng.run_batch(dataclasses.replace(start, radius=radius, count=count, bias=bias, passes=7), 7, 2)
    split_end = device()
    lit = whole.D > 0
    assert lit.mean() > 0.5
    for a, b in zip(whole_end, split_end, strict=True):
        np.testing.assert_allclose(a[lit], b[lit], rtol=1e-6)
    np.testing.assert_allclose(whole.D, first.D + rest.D, rtol=1e-5)
    # ... and it did count: without the catch-up the radius ends larger at most lit pixels
    # (the later passes, gathering at other radii, find other photons: not at every one).
    eng.run_batch(dataclasses.replace(start, passes=6), 6, 3)
    larger = device()[0][lit] > whole_end[0][lit]
    assert larger.mean() > 0.8, larger.mean()


def _job_radius(eng, workers: int, total: int, n: int, offsets: tuple[float, ...], rounds_every: float,
                catch_up: bool = True):
    """A job as the service runs it, by events: `workers` render batches of n passes (the
    first of one pass), worker w a pass in 1 + offsets[w] time units; a batch takes the
    next passes in the job's order and starts from the inputs of the last fold round, which
    folds every accepted batch every `rounds_every` units (without `catch_up` the batch is
    told its inputs hold every pass before it)."""
    state, accepted, next_pass, busy = eng.start(), [], 0, {}

    def start(w: int, now: float, size: int) -> None:
        nonlocal next_pass
        size = min(size, total - next_pass)
        if size > 0:
            inputs = eng.integrator.batch_inputs(state)
            if not catch_up:
                inputs = dataclasses.replace(inputs, passes=next_pass)
            busy[w] = (now + size * (1 + offsets[w]), eng.run_batch(inputs, next_pass, size))
            next_pass += size

    for w in range(workers):
        start(w, 0.0, 1)
    next_round = rounds_every
    while busy:
        w = min(busy, key=lambda v: busy[v][0])
        now, delta = busy.pop(w)
        while next_round <= now:
            for done in accepted:
                state.merge(done)
            accepted, next_round = [], next_round + rounds_every
        accepted.append(delta)
        start(w, now, n)
    for done in accepted:
        state.merge(done)
    return state


@pytest.mark.parametrize("workers, n, offsets, rounds_every", [
    (2, 8, (0.0, 0.05), 6.0), (2, 8, (0.0, 0.6), 6.0), (4, 6, (0.0, 0.3, 0.5, 0.9), 6.0), (3, 4, (0, 0, 0), 2.5),
    (2, 8, (0.6, 0.0), 1.2), (3, 3, (0.9, 0.4, 0.0), 0.7)])
def test_a_job_follows_the_sequential_radius_schedule_whatever_its_batches(make_engine, workers: int, n: int,
                                                                           offsets: tuple[float, ...],
                                                                           rounds_every: float) -> None:
    """Concurrent batches of workers of different speeds, batches that start before the last
    ones are folded, and rounds that fold several batches at once leave the radius where
    one pass at a time would (median over lit pixels within 2%): each pass gathers at the
    radius of its place in the job's pass order and its photons count for N there (sum M),
    whatever the grouping. Without the catch-up for the passes the inputs lack, the radius
    would stay larger."""
    eng = make_engine("furnace", photons_per_pass=1 << 13, seed=12, alpha=0.7)
    total = 48
    sequential = eng.start()
    for k in range(total):
        sequential.merge(eng.run_batch(eng.integrator.batch_inputs(sequential), k, 1))
    lit = sequential.D > 0
    assert lit.mean() > 0.5
    ratio = np.median(_job_radius(eng, workers, total, n, offsets, rounds_every).radius()[lit]
                      / sequential.radius()[lit])
    assert abs(ratio - 1.0) < 0.02, ratio
    without = np.median(_job_radius(eng, workers, total, n, offsets, rounds_every, catch_up=False).radius()[lit]
                        / sequential.radius()[lit])
    assert without > ratio + 0.03, (without, ratio)


