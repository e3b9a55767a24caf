"""Stability where the methods are known to fail (digest 9.2), each with its prediction:

- alpha sweep: variance ~ passes^-alpha and bias ~ passes^-(1-alpha) (Knaus-Zwicker rates,
  dissertation 5.5.4), fitted from independent seeds on point-plane (analytic); alpha = 1
  keeps R0, so its bias plateaus;
- initial radius 1/10 and 10x the default: a transient (noise or bias), then the same rate;
- the stochastic hash with 1/64, 1/8, 1 and 4 table entries per stored photon against the
  exact grid on the same photons: more noise when undersized, never bias;
- a long run of 10^4 passes on furnace: no drift of the float64 sums (error keeps falling,
  the mean stays on the analytic value);
- bias against distance to a hard shadow edge (directional-caustic's sphere shadow, against
  its cached reference): bias concentrates within about a radius of the edge;
- the error estimator's coverage where it is known to fail: 2 and 3 passes (t quantiles
  with 1-2 degrees of freedom, the bias term's own noise) and pixels at illumination edges.

    python -m bench.stability [--full]

Writes bench/out/stability.json and bench/out/stability.png.
"""

from __future__ import annotations

import argparse
import math
import time
from itertools import pairwise

import numpy as np

import worker.error_estimate as ee
from bench.common import BENCH_DIR, bench_engine, save_figure, write_json
from kernels.contract import LUMINANCE
from tests.analytic import FURNACE_L, point_plane
from worker.engine import Engine
from worker.image_io import read_image
from worker.integrators.photon_mapping import GatherInputs
from worker.render_loop import render

ALPHAS = (0.1, 0.5, 2 / 3, 0.7, 0.8, 0.95, 1.0)


def engine(scene: str, res: tuple[int, int] | None, photons: int, **kw: object) -> Engine:
    return bench_engine(scene, res, photons_per_pass=photons, **kw)


def slope(x: list[float], y: list[float]) -> float:
    return float(np.polyfit(np.log(x), np.log(y), 1)[0])


def alpha_sweep(seeds: int, passes: int) -> dict:
    """Per alpha: mean over pixels of the relative variance across seeds, and the relative RMS
    bias, at checkpoints; slopes fitted over the second half of the log range. R0 = 0.5 on a 16x16
    point-plane makes the bias large enough to measure under the noise of the seed mean."""
    checkpoints = sorted({int(round(2 ** k)) for k in np.arange(2, math.log2(passes) + 0.01, 0.5)})
    out = {}
    for alpha in ALPHAS:
        runs = []
        truth = None
        for seed in range(seeds):
            eng = engine("point-plane", (16, 16), 1 << 12, seed=seed, initial_radius=0.5, alpha=alpha)
            truth = point_plane(eng)[0] if truth is None else truth
            snaps: list[np.ndarray] = []

            def snap(st: object, _: float, snaps: list = snaps) -> None:
                if st.passes in checkpoints:
                    snaps.append(st.photon_radiance()[:, 0].copy())

            render(eng, passes=passes, progress=snap)
            runs.append(snaps)
        est = np.array(runs)  # (seeds, checkpoints, pixels)
        var = est.var(axis=0, ddof=1)
        variance = (var / truth ** 2).mean(axis=1)
        # (mean - truth)^2 also holds the seed mean's own noise, var / seeds, which falls
        # like passes^-alpha and would pass for bias: subtract it (unbiased for bias^2)
        bias2 = (((est.mean(axis=0) - truth) ** 2 - var / seeds) / truth ** 2).mean(axis=1)
        # where the estimate of bias^2 is not positive, the bias is below what the seeds resolve
        bias = np.where(bias2 > 0, np.sqrt(np.abs(bias2)), np.nan)
        half = len(checkpoints) // 2
        resolved = [(c, b) for c, b in zip(checkpoints[half:], bias[half:], strict=True) if np.isfinite(b)]
        out[f"{alpha:.3f}"] = {"checkpoints": checkpoints, "relative_variance": variance.tolist(),
                               "relative_bias": [None if not np.isfinite(b) else float(b) for b in bias],
                               "variance_slope": slope(checkpoints[half:], variance[half:].tolist()),
                               "bias_slope": slope(*zip(*resolved, strict=True)) if len(resolved) >= 3 and
                               len(resolved) == len(checkpoints[half:]) else None,
                               "predicted_variance_slope": -alpha, "predicted_bias_slope": -(1 - alpha)}
    return out


def initial_radius(passes: int) -> dict:
    eng = engine("point-plane", (32, 32), 1 << 14, seed=3)
    default = float(eng.start().R0[0])
    truth = point_plane(eng)[0]
    out = {}
    for factor in (0.1, 1.0, 10.0):
        eng = engine("point-plane", (32, 32), 1 << 14, seed=3, initial_radius=default * factor)
        curve: list[float] = []
        render(eng, passes=passes, progress=lambda st, _, curve=curve: curve.append(
            float(np.sqrt(np.mean((st.photon_radiance()[:, 0] / truth - 1) ** 2)))))
        out[f"{factor}x"] = {"r0": default * factor, "relative_rms": curve}
    return out


def hash_table(seeds: int) -> dict:
    """Same photons (same seed), stochastic hash at several table sizes against the exact
    grid: the mean difference over seeds (bias) and the per-pixel RMS difference (extra
    noise). At R0/8, so that cells hold about one photon (Fig. 10.3's regime); at the
    default radius cells hold many and the table size matters little."""
    r = None
    out = {}
    for ratio in (1 / 64, 1 / 8, 1.0, 4.0):
        diffs = []
        for seed in range(seeds):
            exact = engine("cornell-box", (32, 32), 1 << 14, seed=seed, gather="exact")
            r = GatherInputs(exact.start().R0 / 8) if r is None else r
            hashed = engine("cornell-box", (32, 32), 1 << 14, seed=seed, gather="stochastic",
                            hash_entries_per_photon=ratio)
            a, b = hashed.run_batch(r, 0, 1).S.sum(axis=1), exact.run_batch(r, 0, 1).S.sum(axis=1)
            diffs.append(a - b)
        d = np.array(diffs)
        scale = float(np.abs(b).mean())
        out[f"{ratio:g}"] = {"entries_per_photon": ratio,
                             "mean_difference_over_seeds_relative": float(d.mean(axis=0).mean() / scale),
                             "standard_error_relative": float(d.std(ddof=1) / math.sqrt(d.size) / scale),
                             "rms_difference_relative": float(np.sqrt((d ** 2).mean()) / scale)}
    return out


def long_run(passes: int) -> dict:
    eng = engine("furnace", (16, 16), 1 << 12, seed=5)
    checkpoints = {int(10 ** e) for e in np.arange(1, math.log10(passes) + 0.01, 0.25)}
    curve = []

    def observe(st: object, _: float) -> None:
        if st.passes in checkpoints:
            L = st.photon_radiance()[:, 0]
            curve.append({"passes": st.passes, "mean_relative": float(L.mean() / FURNACE_L - 1),
                          "rms_relative": float(np.sqrt(np.mean((L / FURNACE_L - 1) ** 2)))})

    t0 = time.perf_counter()
    render(eng, passes=passes, progress=observe)
    return {"passes": passes, "seconds": time.perf_counter() - t0, "curve": curve,
            "rms_slope_last_decade": slope([c["passes"] for c in curve[-5:]], [c["rms_relative"] for c in curve[-5:]])}


EDGE_REFERENCE = BENCH_DIR / "reference" / "directional-caustic-64x64.exr"


def edge_reference() -> tuple[np.ndarray, np.ndarray]:
    """directional-caustic's cached reference luminance (it has no visible emitter, so this
    is the photon part alone) and each pixel's distance, in pixels, to the nearest edge:
    a pixel whose 4-neighbours differ from it by more than half its value."""
    ref = read_image(EDGE_REFERENCE)[..., :3].astype(np.float64) @ LUMINANCE
    pad = np.pad(ref, 1, mode="edge")
    jumps = [np.abs(pad[1:-1, 1:-1] - pad[:-2, 1:-1]), np.abs(pad[1:-1, 1:-1] - pad[2:, 1:-1]),
             np.abs(pad[1:-1, 1:-1] - pad[1:-1, :-2]), np.abs(pad[1:-1, 1:-1] - pad[1:-1, 2:])]
    ys, xs = np.nonzero(np.max(jumps, axis=0) > 0.5 * np.maximum(ref, 1e-6))
    yy, xx = np.mgrid[0:ref.shape[0], 0:ref.shape[1]]
    dist = np.min(np.hypot(yy[..., None] - ys, xx[..., None] - xs), axis=-1)
    return ref, dist


def shadow_edge(passes: int) -> dict:
    """Relative error of a shorter run against the reference, by distance to an edge."""
    ref, dist = edge_reference()
    eng = engine("directional-caustic", (64, 64), 1 << 15, seed=9)
    st = render(eng, passes=passes)
    img = (st.radiance() @ LUMINANCE).reshape(ref.shape)
    rel = np.abs(img - ref) / np.maximum(ref, 0.05 * ref.mean())
    bins = [0, 1, 2, 3, 5, 8, 13, 99]
    rows = []
    for lo, hi in pairwise(bins):
        m = (dist >= lo) & (dist < hi) & (ref > 0)
        if m.any():
            rows.append({"distance_pixels": [lo, hi], "pixels": int(m.sum()),
                         "mean_relative_error": float(rel[m].mean())})
    return {"passes": passes, "mean_radius": float(st.radius().mean()), "by_distance": rows}


def estimator_failures() -> dict:
    """90% coverage at 2, 3, 8 and 32 passes on directional-caustic, at edge pixels (within 2
    pixels of an edge) and elsewhere."""
    ref, dist = edge_reference()
    truth, near_edge = ref.ravel(), dist.ravel() < 2
    eng = engine("directional-caustic", (64, 64), 1 << 14, seed=11)
    out = []

    def observe(st: object, _: float) -> None:
        if st.passes in (2, 3, 8, 32):
            est = ee.estimate(st, 0.9)
            covered = est.bound >= np.abs(est.luminance - truth)
            out.append({"passes": st.passes, "coverage_90_at_edges": float(covered[est.known & near_edge].mean()),
                        "coverage_90_elsewhere": float(covered[est.known & ~near_edge].mean())})

    render(eng, passes=32, progress=observe)
    return {"directional-caustic": out}


def chart(result: dict) -> None:
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 3, figsize=(16, 9))
    ax = axes[0, 0]
    for a, r in result["alpha_sweep"].items():
        ax.loglog(r["checkpoints"], r["relative_variance"], label=f"a={float(a):.2f} ({r['variance_slope']:.2f})")
    ax.set_title("variance vs passes (fitted slope; predicted -alpha)")
    ax.legend(fontsize=7)
    ax = axes[0, 1]
    for a, r in result["alpha_sweep"].items():
        fit = f"{r['bias_slope']:.2f}" if r["bias_slope"] is not None else "below noise"
        ys = [np.nan if b is None else b for b in r["relative_bias"]]
        ax.loglog(r["checkpoints"], ys, label=f"a={float(a):.2f} ({fit})")
    ax.set_title("RMS bias vs passes (fitted slope; predicted -(1-alpha))")
    ax.legend(fontsize=7)
    ax = axes[0, 2]
    for name, r in result["initial_radius"].items():
        ax.loglog(range(1, len(r["relative_rms"]) + 1), r["relative_rms"], label=f"R0 {name}")
    ax.set_title("initial radius 1/10, 1, 10x the default")
    ax.set_xlabel("passes")
    ax.legend(fontsize=8)
    ax = axes[1, 0]
    h = result["hash_table"]
    xs = [v["entries_per_photon"] for v in h.values()]
    ax.semilogx(xs, [v["rms_difference_relative"] for v in h.values()], "o-", label="RMS difference (noise)")
    ax.errorbar(xs, [v["mean_difference_over_seeds_relative"] for v in h.values()],
                yerr=[3 * v["standard_error_relative"] for v in h.values()], fmt="s",
                label="mean difference +-3 se (bias)")
    ax.axhline(0, color="k", lw=0.6)
    ax.set_xlabel("table entries per stored photon")
    ax.set_title("stochastic hash vs exact grid, same photons")
    ax.legend(fontsize=8)
    ax = axes[1, 1]
    c = result["long_run"]["curve"]
    ax.loglog([p["passes"] for p in c], [p["rms_relative"] for p in c], "o-", label="RMS relative error")
    ax.loglog([p["passes"] for p in c], [abs(p["mean_relative"]) + 1e-7 for p in c], "s-", label="|mean - analytic|")
    ax.set_title(f"furnace, {result['long_run']['passes']} passes: no drift")
    ax.legend(fontsize=8)
    ax = axes[1, 2]
    rows = result["shadow_edge"]["by_distance"]
    ax.bar([f"{r['distance_pixels'][0]}-{r['distance_pixels'][1]}" for r in rows],
           [r["mean_relative_error"] for r in rows])
    ax.set_xlabel("distance to a shadow/caustic edge, pixels")
    ax.set_title("directional-caustic: error by distance to an edge")
    fig.tight_layout()
    save_figure(fig, "stability")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--full", action="store_true")
    args = parser.parse_args()
    result = {
        "alpha_sweep": alpha_sweep(seeds=32 if args.full else 16, passes=512 if args.full else 128),
        "initial_radius": initial_radius(256 if args.full else 96),
        "hash_table": hash_table(seeds=40 if args.full else 20),
        "long_run": long_run(10_000 if args.full else 10_000),
        "shadow_edge": shadow_edge(64),
        "estimator_failures": estimator_failures(),
    }
    write_json("stability", result)
    chart(result)
    for a, r in result["alpha_sweep"].items():
        fit = f"{r['bias_slope']:.2f}" if r["bias_slope"] is not None else "not resolvable"
        print(f"alpha {a}: variance slope {r['variance_slope']:.2f} (pred {-float(a):.2f}), "
              f"bias slope {fit} (pred {-(1 - float(a)):.2f})")
    print("hash", {k: round(v["mean_difference_over_seeds_relative"] / max(v["standard_error_relative"], 1e-12), 2)
                   for k, v in result["hash_table"].items()}, "(mean difference in standard errors)")
    print("long run", result["long_run"]["curve"][-1], result["long_run"]["seconds"])
    print("edge", result["shadow_edge"]["by_distance"])
    print("estimator", result["estimator_failures"])


if __name__ == "__main__":
    main()
