"""Adaptive photon tracing (`sampler: adaptive`, Hachisuka & Jensen 2011) with the real kernels:
the uniform limit, the visible fraction against an independent count, the acceptance the
mutation size is adapted to, replica exchange between two openings, merge order and batch
splits, determinism."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from scipy import stats
from scipy.spatial import cKDTree

from kernels.contract import LUMINANCE
from tests.analytic import (
    FURNACE_L,
    closed_sphere_scene,
    furnace_radiance,
    patch_scene,
    point_plane,
    spot_plane_scene,
)
from tests.conftest import image, render
from worker import adaptive
from worker.error_estimate import estimate
from worker.integrators.photon_mapping import ChainInputs, GatherInputs
from worker.render_loop import render as render_passes
from worker.stats import Accumulators


def _scene_file(tmp_path: Path, scene: dict, name: str = "scene.json") -> Path:
    path = tmp_path / name
    path.write_text(json.dumps(scene))
    return path


def _two_openings_scene() -> dict:
    """A spot light over a black screen with two square openings at x = -1 and x = +1; the
    camera, under the screen, sees the floor where the light through either lands. The
    scene is mirror-symmetric in x, so each opening carries half the visible paths."""
    hole, x0, y = 0.2, 1.0, 1.0
    a, b = x0 - hole / 2, x0 + hole / 2

    def quad(x_lo: float, x_hi: float, z_lo: float, z_hi: float) -> dict:
        return {"type": "quad", "corner": [x_lo, y, z_lo], "edge1": [0, 0, z_hi - z_lo], "edge2": [x_hi - x_lo, 0, 0],
                "material": "black"}

    screen = [quad(-5, -b, -5, 5), quad(-a, a, -5, 5), quad(b, 5, -5, 5)]
    for lo, hi in ((-b, -a), (a, b)):
        screen += [quad(lo, hi, -5, -hole / 2), quad(lo, hi, hole / 2, 5)]
    return {
        "camera": {"position": [0, 0.8, 0], "look_at": [0, 0, 0], "up": [0, 0, -1], "fov": 120,
                   "resolution": [32, 32]},
        "materials": {"floor": {"type": "diffuse", "albedo": [0.5, 0.5, 0.5]},
                      "black": {"type": "diffuse", "albedo": [0.0, 0.0, 0.0]}},
        "shapes": [{"type": "quad", "corner": [-5, 0, -5], "edge1": [0, 0, 10], "edge2": [10, 0, 0],
                    "material": "floor"}, *screen],
        "lights": [{"type": "spot", "position": [0, 11, 0], "direction": [0, -1, 0], "cone_angle": 8.0,
                    "power": [10.0, 10.0, 10.0]}],
    }


def test_every_path_visible_gives_no_mutations_and_the_uniform_image(make_engine, tmp_path) -> None:
    """A spot light whose whole cone lands on the seen plane: every uniform draw is visible,
    so every iteration is an exchange (the paper's uniform limit, dissertation 8.4.4). The radius,
    kept (alpha 1) at almost 3 pixel footprints, leaves no gap between measurement points."""
    path = _scene_file(tmp_path, spot_plane_scene((32, 32)))
    common = {"resolution": (32, 32), "photons_per_pass": 1 << 13, "seed": 5, "initial_radius": 0.3, "alpha": 1.0}
    ada = make_engine(path, sampler="adaptive", **common)
    uni = make_engine(path, **common)
    sa, su = render(ada, 24), render(uni, 24)
    c = sa.counters
    assert c["mutations"] == 0 and c["accepted"] == 0
    # Every iteration's uniform draw is visible and replaces the state, which is splatted once.
    assert c["visible"] == c["draws"] == c["splats"] == 24 * adaptive.iterations(1 << 13)
    assert adaptive.theta(c, 0.234) == 1.0  # nothing to adapt
    # The same estimator with other photon random numbers: per pixel within the noise of
    # both (the two share their measurement points, the same seed's eye passes, so the
    # difference lacks the eye jitter's part of the per-pass noise: a spread below 1).
    la, lu = (image(e, s) @ LUMINANCE for e, s in ((ada, sa), (uni, su)))
    ea, eu = ada.integrator.estimate(sa), uni.integrator.estimate(su)
    lit = (lu > 0.05 * lu.max()).ravel()
    noise = np.hypot(ea.noise, eu.noise)[lit] / stats.t.ppf(0.95, 23)  # standard errors (90% bounds)
    z = (la.ravel() - lu.ravel())[lit] / noise
    assert abs(z.mean()) < 4.0 / math.sqrt(lit.sum()) + 0.05 and z.std() < 1.2
    assert abs(la.mean() / lu.mean() - 1.0) < 0.02


@pytest.mark.parametrize("method", ["sppm", "ppm"])
def test_furnace_mean_is_the_analytic_radiance(make_engine, method: str) -> None:
    """The camera sees part of the furnace (V_c ~ 0.2): the chains' photons crowd into its
    view, and each pass's V_k / splats scales them back to the analytic radiance."""
    eng = make_engine("furnace", photons_per_pass=1 << 15, seed=3, sampler="adaptive", method=method)
    state = render(eng, 24)
    assert 0.05 < adaptive.visible_fraction(state.counters) < 0.5
    mean = image(eng, state).mean()
    assert abs(mean / FURNACE_L - 1.0) < 0.02, (mean, FURNACE_L)


def test_long_paths_beyond_the_photon_cache(make_engine, tmp_path) -> None:
    """Albedo 0.9: a path stores 10 photons on average and 18% store more than DEPOSIT_CACHE
    (16), so their states are traced again at every splat instead of re-counted. The camera
    sees most of the sphere (V_c ~ 0.83): the other iterations mutate."""
    path = _scene_file(tmp_path, closed_sphere_scene((0.9, 0.9, 0.9)))
    eng = make_engine(path, photons_per_pass=1 << 13, seed=8, sampler="adaptive")
    state = render(eng, 16)
    mean = image(eng, state).mean()
    truth = float(furnace_radiance(0.9))
    assert abs(mean / truth - 1.0) < 0.02, (mean, truth, state.counters)
    assert state.counters["mutations"] > 0.01 * state.counters["draws"], state.counters


def test_stochastic_hash_with_chains_is_unbiased_on_average(make_engine) -> None:
    """With the stochastic hash a kept chain state is stored again (the hash counts photons,
    not counts), each copy with its own key: the mean stays the analytic one."""
    eng = make_engine("point-plane", photons_per_pass=1 << 16, seed=6, sampler="adaptive", gather="stochastic")
    state = render(eng, 32)
    assert state.counters["mutations"] > 0
    rel = image(eng, state)[..., 0] / point_plane(eng)[0].reshape(eng.arrays.height, eng.arrays.width) - 1.0
    assert abs(rel.mean()) < 0.015, rel.mean()


def test_point_plane_matches_analytic_radiance(make_engine) -> None:
    """Per pixel against the closed form; every photon gathered (exact grid). At V_c ~ 0.28
    the chains' correlated photons leave more noise than uniform tracing's (sampler auto
    keeps uniform photons here): the RMS error is held to the job's own noise estimate."""
    eng = make_engine("point-plane", photons_per_pass=1 << 17, seed=5, sampler="adaptive")
    state = render(eng, 48)
    rel = image(eng, state)[..., 0] / point_plane(eng)[0].reshape(eng.arrays.height, eng.arrays.width) - 1.0
    assert abs(rel.mean()) < 0.015, rel.mean()
    est = eng.integrator.estimate(state)
    bound = np.sqrt(np.mean((est.noise / est.luminance)[est.known] ** 2))  # 90% bounds, relative
    assert np.sqrt(np.mean(rel ** 2)) < bound, (np.sqrt(np.mean(rel ** 2)), bound)


@pytest.mark.parametrize("scene", ["furnace", "point-plane"])
def test_error_bounds_cover_within_five_points_of_nominal(make_engine, scene: str) -> None:
    """The error estimate with the adaptive sampler (every pass's sums in uniform photons,
    scaled by the pass's own V_k / splats): the share of pixels whose bound holds
    the actual error, at 50% and 90%, after 8, 24 and 64 passes (as tests/test_error_estimation.py)."""
    eng = make_engine(scene, photons_per_pass=1 << 15, seed=31, sampler="adaptive")
    truth = FURNACE_L if scene == "furnace" else point_plane(eng)[0]
    state = eng.start()
    for k in range(64):
        state.merge(eng.render_batch(state, k, 1))
        if k + 1 in (8, 24, 64):
            for confidence in (0.5, 0.9):
                est = estimate(state, confidence)
                share = float(np.mean(est.bound[est.known] >= np.abs(est.luminance - truth)[est.known]))
                assert abs(share - confidence) <= 0.05, (k + 1, confidence, share)
    assert adaptive.visible_fraction(state.counters) < 0.5  # the chains did the work


def _unpack_dirs(bits: np.ndarray) -> np.ndarray:
    """kernels/materials.cl unpack_dir, vectorised."""
    p = np.stack([(bits & 0xFFFF), (bits >> 16)], axis=-1).astype(np.float64) / 65535.0 * 2.0 - 1.0
    v = np.concatenate([p, 1.0 - np.abs(p).sum(axis=-1, keepdims=True)], axis=-1)
    low = v[:, 2] < 0.0
    v[low, :2] = (1.0 - np.abs(p[low][:, ::-1])) * np.where(p[low] >= 0.0, 1.0, -1.0)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _inside_cut(cut: np.ndarray, n: np.ndarray, v: np.ndarray, r: float) -> bool:
    """kernels/eye_pass.cl inside_cut, for one point and photon: within the polygon of the
    coverage rays' cut points (8 rays, 8 bits each over CUT_REACH r, 255 for a ray that found
    no cut: its end; the rim between two such rays; nothing between two cut at the centre)."""
    if int(cut[0]) & int(cut[1]) == 0xFFFFFFFF:
        return True
    s = 1.0 if n[2] >= 0.0 else -1.0  # materials.cl onb (Duff et al. 2017)
    a = -1.0 / (s + n[2])
    c = n[0] * n[1] * a
    t = np.array([1.0 + s * n[0] * n[0] * a, s * c, -s * n[0]])
    b = np.array([c, s + n[1] * n[1] * a, -n[1]])
    p = np.array([v @ t, v @ b])
    step, phi0 = 2.0 * math.pi / 8, float(np.array(cut[2], np.uint32).view(np.float32))
    k = math.floor((math.atan2(p[1], p[0]) - phi0) / step) & 7
    k1 = (k + 1) & 7
    reach = 1.0 / math.cos(math.pi / 8)
    codes = [(int(cut[j >> 2]) >> (8 * (j & 3))) & 0xFF for j in (k, k1)]
    if codes == [255, 255]:
        return True
    if codes == [0, 0]:
        return False
    cuts = [code / 255.0 * reach if code < 255 else reach for code in codes]
    angles = (phi0 + k * step, phi0 + (k + 1) * step)
    p0, p1 = (q * r * np.array([math.cos(x), math.sin(x)]) for q, x in zip(cuts, angles, strict=True))
    e, w = p1 - p0, p - p0
    return e[0] * w[1] - e[1] * w[0] >= 0.0


def _visible_paths(eng, r: float) -> int:
    """Independent count of the visible photon paths of the uniform pass just run at radius
    `r` everywhere: its stored photons against its measurement points, by a k-d tree on the
    host (within the radius and the disc's covered part, arrived on the eye's side, normals within 45 degrees),
    paths by their keys."""
    import pyopencl as cl

    ps, dev, n = eng.passes, eng.device, eng.arrays.n_pixels
    m = ps.photons_stored

    def read(buf, dtype, shape):
        out = np.empty(shape, dtype)
        cl.enqueue_copy(dev.queue, out, buf)
        return out

    mp_pos, mp_nrm = read(ps.mp_pos, np.float32, (n, 4)), read(ps.mp_nrm, np.float32, (n, 4))
    mp_cut = read(ps.mp_cut, np.uint32, (n, 4))
    ph_pos = read(ps.ph_pos, np.float32, (ps.capacity, 4))[:m]
    ph_dirs = read(ps.ph_dirs, np.uint32, (ps.capacity, 2))[:m]
    ph_key = read(ps.ph_key, np.uint64, ps.capacity)[:m]
    has = mp_pos[:, 3] > 0
    pts, nrm = mp_pos[has, :3].astype(np.float64), mp_nrm[has, :3].astype(np.float64)
    cuts = mp_cut[has]
    incoming, normal = _unpack_dirs(ph_dirs[:, 0]), _unpack_dirs(ph_dirs[:, 1])
    visible = np.zeros(m, bool)
    for i, near in enumerate(cKDTree(pts).query_ball_point(ph_pos[:, :3].astype(np.float64), r)):
        if near:
            nn = nrm[near]
            ok = (nn @ incoming[i] > 0.0) & (nn @ normal[i] > math.cos(math.pi / 4))
            visible[i] = any(_inside_cut(cuts[j], nrm[j], ph_pos[i, :3] - pts[j], r)
                             for j, good in zip(near, ok, strict=True) if good)
    return len(np.unique((ph_key[visible] >> np.uint64(12)) & np.uint64((1 << 24) - 1)))


def test_visible_fraction_matches_an_independent_count(make_engine) -> None:
    """The chains' V_c (their uniform draws) and a k-d tree count over a uniform pass's
    photon paths, same measurement points and radius: two binomial samples of one V_c."""
    common = {"resolution": (32, 32), "photons_per_pass": 1 << 14, "seed": 9, "initial_radius": 0.15}
    ada, uni = make_engine("gap", sampler="adaptive", **common), make_engine("gap", **common)
    r = np.full(ada.arrays.n_pixels, 0.15)
    chains = ChainInputs(theta=0.3, chains=64)
    draws = visible = independent = 0
    for k in range(3):
        c = ada.run_batch(GatherInputs(r, None, chains), k, 1).counters
        draws, visible = draws + c["draws"], visible + c["visible"]
        uni.run_batch(GatherInputs(r), k, 1)
        independent += _visible_paths(uni, float(np.float32(r[0])))  # the radius as the device holds it
    n = 3 * (1 << 14)
    assert draws == n
    v1, v2 = visible / n, independent / n
    assert 0.05 < v2 < 0.95  # a scene where visibility decides something
    pooled = (visible + independent) / (2 * n)
    z = (v1 - v2) / math.sqrt(pooled * (1 - pooled) * 2 / n)
    assert abs(z) < 3.3, (v1, v2)  # 99.9% two-sided


@pytest.mark.parametrize("gather", ["exact", "stochastic"])
def test_a_chain_pass_brings_a_uniform_pass_worth_whatever_its_iterations(make_engine, tmp_path, gather: str) -> None:
    """SPPM's radius rule takes a pixel's count scale from its first photons and shrinks by
    (N + alpha M) / (N + M) after, so every pass must bring the same expected photon count
    M, and the image the same expected flux, whichever sampler and pass size. A patch seen
    through 12 degrees (V_c ~ 0.03), same points and radius: per pass, the total count
    (sum of D pi r^2) and flux of uniform passes and of chain passes of a full and a quarter
    pass of iterations agree within 4 standard errors (passes are independent). Scaled by
    the pooled V_c at display time instead, the chains' counts were 10-35x a uniform
    pass's, and a job's first pass (all iterations, no counters yet) twice its later ones."""
    photons, passes, r0 = 1 << 12, 32, 0.05
    common = {"photons_per_pass": photons, "seed": 5, "initial_radius": r0, "gather": gather}
    path = _scene_file(tmp_path, patch_scene(12.0))
    uni, ada = make_engine(path, **common), make_engine(path, sampler="adaptive", **common)
    r = np.full(uni.arrays.n_pixels, r0)

    def per_pass(eng, inputs: GatherInputs) -> np.ndarray:
        out = []
        for k in range(passes):
            d = eng.run_batch(inputs, k, 1)
            out.append((float((d.sums["D"] * math.pi * r * r).sum()), float(d.sums["S"].sum())))
            if inputs.chains is not None:
                assert d.counters["mutations"] > 0 and d.counters["visible"] < 0.1 * d.counters["draws"]
        return np.array(out)

    base = per_pass(uni, GatherInputs(r))
    for iterations in (photons, photons // 4):
        chains = per_pass(ada, GatherInputs(r, None, ChainInputs(theta=0.1, chains=16, iterations=iterations)))
        se = np.sqrt(base.var(axis=0, ddof=1) / passes + chains.var(axis=0, ddof=1) / passes)
        assert np.all(np.abs(chains.mean(axis=0) - base.mean(axis=0)) < 4.0 * se), (iterations, base.mean(axis=0),
                                                                                    chains.mean(axis=0), se)


@pytest.mark.parametrize("target", [0.05, 0.234, 0.5])
def test_acceptance_reaches_the_target(make_engine, tmp_path, target: float) -> None:
    """A patch seen through a 6 degree view of a point-lit plane: V_c ~ 0.008, so the
    acceptance runs from V_c (huge mutations) to 1 (tiny ones) and every target is reachable
    A pass runs
    photons / 8 iterations (adaptive.iterations), nearly all mutating: the last 24 of 64
    passes give at least 5,000 mutations (the acceptance's standard error below 0.007)."""
    eng = make_engine(_scene_file(tmp_path, patch_scene(6.0)), photons_per_pass=1 << 15, seed=3,
                      sampler="adaptive", target_acceptance=target)
    state = render(eng, 40)
    before = dict(state.counters)
    render_passes(eng, passes=64, state=state)  # the last 24 passes measure the acceptance
    mutations = state.counters["mutations"] - before["mutations"]
    accepted = state.counters["accepted"] - before["accepted"]
    assert mutations > 5_000
    assert abs(accepted / mutations - target) < 0.02, (accepted / mutations, adaptive.theta(state.counters, target))
    v_c = adaptive.visible_fraction(state.counters)
    assert v_c < 0.02


def test_replica_exchange_finds_both_openings_in_proportion(make_engine, tmp_path) -> None:
    """One chain a pass, theta at its floor 0.001: the openings lie 0.5 apart in the emission
    angle's dimension, so a mutation lands in the other opening about once a pass. With
    replica exchange (~150 exchanges a pass at V_c ~ 1%) the light through the two splits
    evenly, the scene being symmetric; by mutations alone a pass often stays in the opening
    its chain started in."""
    eng = make_engine(_scene_file(tmp_path, _two_openings_scene()), photons_per_pass=1 << 14, seed=21,
                      sampler="adaptive", initial_radius=0.05)
    n = eng.arrays.n_pixels
    inputs = GatherInputs(np.full(n, 0.05), None, ChainInputs(theta=adaptive.THETA_MIN, chains=1))

    def left_share(delta) -> float:
        lum = (delta.S @ LUMINANCE).reshape(eng.arrays.height, eng.arrays.width)
        return float(lum[:, :eng.arrays.width // 2].sum() / lum.sum())

    shares = {}
    for exchange in (True, False):
        eng.passes.replica_exchange = exchange
        deltas = [eng.run_batch(inputs, k, 1) for k in range(8)]
        assert all(d.counters["started"] == 1 for d in deltas)
        shares[exchange] = np.array([left_share(d) for d in deltas])
    v_c = sum(d.counters["visible"] for d in deltas) / sum(d.counters["draws"] for d in deltas)
    assert 0.002 < v_c < 0.05
    both, alone = shares[True], shares[False]
    # Per pass ~150 runs of geometric length split between the openings: a spread of about
    # 0.06 in theory, 0.06 to 0.15 over seeds 21..32 (the chains' random numbers drawn two
    # ways); by mutations alone it is above 0.25.
    assert abs(both.mean() - 0.5) < 0.06 and both.std() < 0.18, both
    assert alone.std() > 0.25 and (np.minimum(alone, 1.0 - alone) < 0.05).sum() >= 2, alone


def _adaptive_engine(make_engine, gather: str = "exact"):
    """gap at 24x24 (V_c ~ 0.5), chains in every pass."""
    return make_engine("gap", resolution=(24, 24), photons_per_pass=1 << 12, seed=4, sampler="adaptive", gather=gather)


@pytest.mark.parametrize("passes", [1, 2])
def test_batches_merge_in_any_order(make_engine, passes: int) -> None:
    """Passes 1..6 from one state (pass 0's, which gives V_c and theta) in batches of `passes`, as
    concurrent workers would run them, merged forwards and backwards: the same image,
    counters and next theta. (How passes split into batches moves the radii within a
    batch, stats.py, so only the order is free.)"""
    eng = _adaptive_engine(make_engine)
    start = eng.start()
    first = eng.run_batch(eng.integrator.batch_inputs(start), 0, 1)

    def after_first() -> Accumulators:
        state = eng.integrator.start({"R0": start.R0})
        eng.integrator.merge(state, first)
        return state

    inputs = eng.integrator.batch_inputs(after_first())
    deltas = [eng.run_batch(inputs, k, passes) for k in range(1, 7, passes)]
    results = []
    for order in (deltas, deltas[::-1]):
        state = after_first()
        for d in order:
            eng.integrator.merge(state, d)
        results.append(state)
    assert results[1].counters == results[0].counters
    assert eng.integrator.batch_inputs(results[1]).chains == eng.integrator.batch_inputs(results[0]).chains
    np.testing.assert_allclose(eng.integrator.image(results[1]), eng.integrator.image(results[0]), rtol=1e-12,
                               atol=1e-15)
    assert results[0].counters["splats"] > 0 and results[0].counters["mutations"] > 0


@pytest.mark.parametrize("gather", ["exact", "stochastic"])
def test_same_seed_same_image(make_engine, gather: str) -> None:
    """Two engines, same settings: the same passes bit for bit (sums and counters)."""
    a, b = _adaptive_engine(make_engine, gather), _adaptive_engine(make_engine, gather)
    sa, sb = render(a, 3), render(b, 3)
    assert sa.counters == sb.counters
    for name in sa.sums:
        np.testing.assert_array_equal(sa.sums[name], sb.sums[name])


def test_cli_renders_adaptive_says_what_auto_does_and_refuses_an_unknown_sampler(tmp_path: Path) -> None:
    from tests.helpers import SMALL, render_cli
    from worker.image_io import read_metadata

    out = tmp_path / "gap.exr"
    proc = render_cli("gap", "--passes", "3", *SMALL, "--sampler", "adaptive", "--target-acceptance", "0.3",
                      "--out", str(out))
    assert proc.returncode == 0 and "sampler auto" not in proc.stderr, proc.stderr
    meta = read_metadata(out)
    counters = json.loads(meta["counters"])
    assert counters["draws"] == 3 * adaptive.iterations(4096), counters  # every pass runs chains
    assert 0 < counters["visible"] < counters["draws"] and counters["mutations"] > 0, counters
    assert json.loads(meta["settings"])["sampler"] == "adaptive"
    proc = render_cli("gap", "--passes", "3", *SMALL, "--out", str(out))  # sampler auto, still measuring
    assert proc.returncode == 0, proc.stderr
    said = f"photonfarm: sampler auto: measuring (3 of passes 0-{adaptive.MEASURE_PASSES - 1} merged)"
    assert said in proc.stderr, proc.stderr
    proc = render_cli("gap", "--passes", "3", *SMALL, "--sampler", "mcmc", "--out", str(out))
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
    assert "invalid choice: 'mcmc'" in proc.stderr.strip().splitlines()[-1], proc.stderr


def test_settings_name_the_sampler_in_their_errors() -> None:
    from pydantic import ValidationError

    from service.models import JobRequest

    for settings, loc, text in (({"sampler": "mcmc"}, ("settings", "sampler"), "'auto', 'uniform' or 'adaptive'"),
                                ({"target_acceptance": 1.0}, ("settings", "target_acceptance"), "less than 1"),
                                ({"method": "vcm", "sampler": "adaptive"}, ("settings", "sampler"), "sppm and ppm")):
        with pytest.raises(ValidationError) as info:
            JobRequest.model_validate({"scene_name": "gap", "settings": settings})
        error = info.value.errors()[0]
        assert error["loc"] == loc and text in error["msg"], error


def test_nothing_visible_falls_back_to_uniform_tracing(make_engine, tmp_path) -> None:
    """A point light under the seen plane: no path is ever visible. The chains find no start,
    every pass is uniform tracing that found nothing: a black image, no NaN, no hang, and
    the error estimate still answers."""
    scene = patch_scene(60.0)
    scene["lights"][0]["position"] = [0, -1, 0]
    eng = make_engine(_scene_file(tmp_path, scene), photons_per_pass=1 << 12, seed=2, sampler="adaptive")
    state = render(eng, 3)
    c = state.counters
    assert c["draws"] == 3 * adaptive.iterations(1 << 12)
    assert c["visible"] == c["splats"] == c["started"] == c["mutations"] == 0
    img = image(eng, state)
    assert np.all(img == 0.0)
    est = eng.integrator.estimate(state)
    assert np.all(np.isfinite(est.relative)) and est.average == 1.0


def _measured(uniform_us: int, chain_us: int, draws: int, visible: int, splats: int, passes: int = 8) -> dict[str, int]:
    """Counters as `passes` uniform and `passes` chain measuring passes would leave them
    (adaptive.measured, summed), with a few of the pooled counters beside them."""
    counters = {"draws": 7 * draws, "visible": 5 * visible, "splats": 3}  # not the measuring passes'
    for _ in range(passes):
        for name, value in [*adaptive.measured(uniform_us * 1e-6, None).items(),
                            *adaptive.measured(chain_us * 1e-6, {"draws": draws, "visible": visible, "splats": splats,
                                                                 "mutations": draws - visible,
                                                                 "accepted": (draws - visible) // 4}).items()]:
            counters[name] = counters.get(name, 0) + value
    return counters


def test_auto_chooses_by_visible_paths_a_second_from_its_measuring_passes_alone() -> None:
    """sampler auto's choice from synthetic counters: a uniform pass of 2^18 photons at V_c
    1e-3 brings 262 visible paths; a chain pass of 2^15 iterations splats about that many
    times, so the ratio is 125 at equal times, and crosses MIN_VISIBLE_RATIO as the chain
    pass gets slower. No choice before all MEASURE_PASSES are merged; the counters the
    other passes pool (draws, visible) change nothing; the figures are the counters'."""
    photons, draws, visible, splats = 1 << 18, 1 << 15, 33, 1 << 15
    v_c = visible / draws
    half = adaptive.MEASURE_PASSES // 2
    assert adaptive.choice(_measured(200_000, 200_000, draws, visible, splats, half - 1), photons) is None
    even = adaptive.choice(_measured(200_000, 200_000, draws, visible, splats, half), photons)
    assert even is not None and even.chains
    assert even.visible_fraction == pytest.approx(v_c) and even.uniform_seconds == pytest.approx(0.2)
    assert even.ratio == pytest.approx(splats / (v_c * photons), rel=1e-9)
    assert even.acceptance == pytest.approx(0.25, abs=0.01)
    slowest_chains = even.ratio / adaptive.MIN_VISIBLE_RATIO  # chain pass seconds over uniform's at the threshold
    for factor, chains in ((0.9, True), (1.1, False)):
        c = adaptive.choice(_measured(200_000, round(200_000 * slowest_chains * factor), draws, visible, splats,
                                      half), photons)
        assert c is not None and c.chains == chains, (factor, c)
        assert ("sampler auto: chains:" if chains else "sampler auto: uniform photons:") in c.note()
        assert f"V_c {v_c:.3g}" in c.note() and f"{c.ratio:.3g} times" in c.note()
    none_visible = adaptive.choice(_measured(200_000, 100_000, draws, 0, 0, half), photons)
    assert none_visible is not None and not none_visible.chains and none_visible.ratio == 0.0


@pytest.mark.parametrize("scene, side, chains", [("slit-room", 32, True), ("cornell-box", 24, False)])
def test_auto_chooses_chains_where_few_paths_are_visible(make_engine, scene: str, side: int, chains: bool) -> None:
    """The real sampler, rendering as the CLI does: slit-room (V_c ~ 1e-3, a room lit through
    a slit) chooses chains, cornell-box (V_c ~ 0.8) uniform photons, after MEASURE_PASSES
    passes; the measuring passes alternate (odd ones run chains), and the next batch
    follows the choice, which the notes state with its ratio."""
    eng = make_engine(scene, resolution=(side, side), photons_per_pass=1 << 16, seed=3)
    assert eng.settings.sampler == "auto"
    state = eng.start()
    for k in range(adaptive.MEASURE_PASSES):
        inputs = eng.integrator.batch_inputs(state)
        assert inputs.chains is not None and inputs.chains.measuring
        delta = eng.run_batch(inputs, k, 1)
        assert ("mutations" in delta.counters) == (k % 2 == 1), (k, delta.counters)
        eng.integrator.merge(state, delta)
    choice = adaptive.choice(state.counters, 1 << 16)
    assert choice is not None and choice.chains == chains, choice
    assert (choice.visible_fraction < 0.01) == chains
    inputs = eng.integrator.batch_inputs(state)
    assert (inputs.chains is not None and not inputs.chains.measuring) if chains else inputs.chains is None
    assert eng.integrator.notes(state.counters) == [choice.note()]
    if chains:
        assert choice.ratio >= adaptive.MIN_VISIBLE_RATIO
    else:
        assert choice.ratio < adaptive.MIN_VISIBLE_RATIO


def test_auto_uniform_passes_are_the_uniform_samplers(make_engine) -> None:
    """While sampler auto measures, its even passes and those after the window are the
    uniform sampler's bit for bit (a batch of passes 14..17 from the same inputs: 14, 16
    and 17 uniform, 15 chains); once it chose uniform photons its batches are."""
    common = {"resolution": (24, 24), "photons_per_pass": 1 << 12, "seed": 3}
    auto, uni = make_engine("cornell-box", **common), make_engine("cornell-box", sampler="uniform", **common)
    state = auto.start()
    inputs = auto.integrator.batch_inputs(state)
    plain = GatherInputs(inputs.radius, inputs.bias, count=inputs.count, passes=inputs.passes)
    window = adaptive.MEASURE_PASSES
    for first in (window - 2, window - 1):  # uniform pass, then chains pass, first in the batch
        a, u = auto.run_batch(inputs, first, 1), uni.run_batch(plain, first, 1)
        same = all(np.array_equal(a.sums[name], u.sums[name]) for name in u.sums)
        assert same == (first % 2 == 0), first
        kind = "uniform" if first % 2 == 0 else "chain"
        assert a.counters[f"{adaptive.MEASURED}{kind}_passes"] == 1 and a.counters[f"{adaptive.MEASURED}{kind}_us"] > 0
    a, u = auto.run_batch(inputs, window, 2), uni.run_batch(plain, window, 2)
    for name in u.sums:
        np.testing.assert_array_equal(a.sums[name], u.sums[name])
    assert not any(name.startswith(adaptive.MEASURED) for name in a.counters), a.counters
    uniform = _measured(100_000, 100_000, 1 << 10, 800, 1 << 10, adaptive.MEASURE_PASSES // 2)
    assert adaptive.choice(uniform, 1 << 12) is not None
    assert auto.integrator.chain_inputs(uniform) is None


def test_auto_applies_to_every_method_and_adaptive_to_photon_mapping() -> None:
    """auto is every method's default (the methods that trace no photon paths for a
    gather have nothing to choose); adaptive is refused where it cannot apply."""
    from worker.integrators import integrator_for
    from worker.settings import Settings

    for method in ("sppm", "ppm", "vcm", "bpt", "lt"):
        settings = Settings(method=method).for_frame(8, 8)
        assert settings.sampler == "auto"
        assert integrator_for(settings).notes({}) == ([adaptive.measuring_note({})] if method in ("sppm", "ppm")
                                                      else [])


@pytest.mark.parametrize("batches", [1, 8, 40, 200])
@pytest.mark.parametrize("best", [0.002, 0.3, 20.0])
def test_theta_controller_is_the_same_for_any_number_of_concurrent_batches(batches: int, best: float) -> None:
    """The controller alone on a model acceptance A(theta) = 1 / (1 + (theta / best)^1.5)
    (falling from 1 to 0, A* = 0.234 near theta = 2.2 best) with binomial noise: rounds of
    `batches` concurrent 8-pass batches, each from the merged counters of the rounds
    before, reach the target within 0.03 by the fourth round from 1.0, best 1/500 to 20
    times theta's start, and stay there, whatever the number of concurrent batches."""
    rng = np.random.default_rng(5)
    target, counters = 0.234, {}

    def acceptance(theta: float) -> float:
        return 1.0 / (1.0 + (theta / best) ** 1.5)

    rounds = []
    for _ in range(8):
        theta = adaptive.theta(counters, target)  # every batch of the round starts from the same state
        rounds.append(acceptance(theta))
        for _ in range(batches * 8):
            mutations = 2_000
            accepted = int(rng.binomial(mutations, acceptance(theta)))
            for name, value in adaptive.binned(theta, mutations, accepted).items():
                counters[name] = counters.get(name, 0) + value
    assert all(abs(a - target) < 0.03 for a in rounds[3:]), rounds


def test_concurrent_batches_reach_the_target_acceptance(make_engine, tmp_path) -> None:
    """The real sampler on the patch scene (V_c ~ 0.008): rounds of 8 concurrent 8-pass
    batches, all from the round's merged state, as 8 workers run them; the fourth round's
    acceptance is within 0.03 of the target."""
    eng = make_engine(_scene_file(tmp_path, patch_scene(6.0)), photons_per_pass=1 << 13, seed=3,
                      sampler="adaptive")
    target = eng.settings.target_acceptance
    state = eng.start()
    eng.integrator.merge(state, eng.run_batch(eng.integrator.batch_inputs(state), 0, 1))  # V_c
    acceptance = []
    for r in range(4):
        inputs = eng.integrator.batch_inputs(state)
        deltas = [eng.run_batch(inputs, 1 + 64 * r + 8 * b, 8) for b in range(8)]
        mutations = sum(d.counters["mutations"] for d in deltas)
        acceptance.append(sum(d.counters["accepted"] for d in deltas) / mutations)
        for d in deltas:
            eng.integrator.merge(state, d)
    assert abs(acceptance[3] - target) < 0.03, acceptance
