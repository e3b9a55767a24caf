"""Progressive error estimation: its overhead per pass, its coverage (Fig. 6.6), the bias
significance sweep behind z, and termination at halving thresholds (Table 6.2).

    python -m bench.error_estimation [--full]

Overhead: the same job rendered with the error sums compiled in and out, side by side,
plus the host's estimate per merge. Coverage: the share of pixels whose bound is at least
the actual error against the analytic answer (furnace, point-plane) or the cached
reference (cornell-caustics, photon part only). Termination: passes until the estimated
average relative error falls to T, for T halving, with the estimate and the actual error
(the same definition, worker/error_estimate.actual_average) at that point: a threshold is
met by the estimate, and the actual error at termination shows how far the job overshot
(merging one pass at a time, and 8 at once as a worker's batch does).
Writes bench/out/error_estimation.json and .png.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from itertools import pairwise

import numpy as np

import worker.error_estimate as ee
from bench.common import BENCH_DIR, bench_engine, save_figure, write_json
from kernels.contract import LUMINANCE
from tests.analytic import FURNACE_L, point_plane
from worker.engine import Engine
from worker.image_io import read_image
from worker.render_loop import render

REFERENCE = BENCH_DIR / "reference" / "cornell-caustics-48x48.exr"
Truth = Callable[[Engine], np.ndarray | float]
CASES: dict[str, tuple[tuple[int, int] | None, int, Truth]] = {
    "furnace": (None, 1 << 15, lambda eng: FURNACE_L),
    "point-plane": (None, 1 << 15, lambda eng: point_plane(eng)[0]),
    "cornell-caustics": ((48, 48), 1 << 12, lambda eng: read_image(REFERENCE).reshape(-1, 3) @ LUMINANCE),
}


def overhead(passes: int) -> dict:
    """The estimator's cost per pass: the gather kernel's device time with the error sums
    compiled in and out (the only kernel they touch), plus the host's estimate per merge,
    against the wall time of a pass. Wall times alone differ by more than that from run to run."""
    out: dict[str, list[float]] = {}
    for on in (False, True, False, True):  # interleaved, to spread any drift of the machine
        eng = bench_engine("cornell-caustics", (256, 256), photons_per_pass=1 << 18, seed=3, error_estimation=on)
        st = render(eng, passes=1)  # warm-up
        gather0 = eng.times.seconds["gather"]
        host = [0.0]

        def observe(state: object, _: float, on: bool = on, host: list[float] = host) -> None:
            if on:
                h0 = time.perf_counter()
                ee.estimate(state, 0.9)
                host[0] += time.perf_counter() - h0

        t0 = time.perf_counter()
        render(eng, passes=passes + 1, progress=observe, state=st)
        key = "with" if on else "without"
        out.setdefault(f"wall_{key}", []).append((time.perf_counter() - t0 - host[0]) / passes)
        out.setdefault(f"gather_{key}", []).append((eng.times.seconds["gather"] - gather0) / passes)
        if on:
            out.setdefault("host_estimate", []).append(host[0] / passes)
    per_pass = {k: float(np.median(v)) for k, v in out.items()}
    per_pass["overhead_fraction"] = (per_pass["gather_with"] - per_pass["gather_without"]
                                     + per_pass["host_estimate"]) / per_pass["wall_without"]
    return per_pass


def coverage(passes: list[int], z_values: list[float]) -> dict:
    result: dict = {}
    for scene, (res, photons, truth_of) in CASES.items():
        eng = bench_engine(scene, res, photons_per_pass=photons, seed=31)
        truth = truth_of(eng)

        def observe(st: object, _: float, scene: str = scene, truth: object = truth) -> None:
            if st.passes not in passes:
                return
            for z in z_values:
                for conf in (0.5, 0.9):
                    est = ee.estimate(st, conf, significance=z)
                    covered = est.bound >= np.abs(est.luminance - truth)
                    result.setdefault(scene, []).append({"passes": st.passes, "z": z, "confidence": conf,
                                                         "coverage": float(covered[est.known].mean())})

        render(eng, passes=max(passes), progress=observe)
    return result


def termination(thresholds: list[float], max_passes: int, batch: int = 1) -> dict:
    """Per scene and confidence, for each threshold T (halving): the passes at which the
    estimated average first fell to T, the estimate and the actual error then. Batches of
    `batch` passes merge at once, as on a worker, so the estimate is seen only between them."""
    result = {}
    for scene in ("furnace", "point-plane", "cornell-caustics"):
        res, photons, truth_of = CASES[scene]
        for conf in (0.5, 0.9):
            eng = bench_engine(scene, res, photons_per_pass=photons, seed=5, confidence=conf)
            truth = truth_of(eng)
            pending = sorted(thresholds, reverse=True)
            rows: list[dict] = []
            st = eng.start()
            while pending and st.passes < max_passes:
                eng.integrator.merge(st, eng.render_batch(st, st.passes, batch))
                est = eng.integrator.estimate(st)
                while pending and est.average <= pending[0]:
                    rows.append({"threshold": pending.pop(0), "passes": st.passes, "estimated": est.average,
                                 "actual": ee.actual_average(est, truth)})
            result[f"{scene} @ {conf}"] = rows
    return result


def chart(result: dict) -> None:
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 4, figsize=(21, 4.6))
    z = ee.BIAS_SIGNIFICANCE
    for scene, rows in result["coverage"].items():
        for conf, style in ((0.5, "o-"), (0.9, "s--")):
            pts = [(r["passes"], r["coverage"]) for r in rows if r["z"] == z and r["confidence"] == conf]
            axes[0].plot(*zip(*pts, strict=True), style, label=f"{scene} {int(conf * 100)}%")
    for conf in (0.5, 0.9):
        axes[0].axhspan(conf - 0.05, conf + 0.05, color="grey", alpha=0.15)
    axes[0].set_xscale("log")
    axes[0].set_xlabel("passes")
    axes[0].set_ylabel("share of pixels with bound >= actual error")
    axes[0].set_title(f"coverage (Fig. 6.6), z = {z}; bands: nominal +-5 points")
    axes[0].legend(fontsize=7)
    last = max(r["passes"] for rows in result["coverage"].values() for r in rows)
    for scene, rows in result["coverage"].items():
        for conf, style in ((0.5, "o-"), (0.9, "s--")):
            pts = sorted((r["z"], r["coverage"]) for r in rows if r["passes"] == last and r["confidence"] == conf)
            axes[1].plot(*zip(*pts, strict=True), style, label=f"{scene} {int(conf * 100)}%")
    axes[1].axvline(z, color="k", lw=0.8)
    axes[1].set_xlabel("bias significance z (standard errors)")
    axes[1].set_title(f"coverage at {last} passes against z")
    axes[1].legend(fontsize=7)
    for name, rows in result["termination"].items():
        if rows:
            axes[2].loglog([r["threshold"] for r in rows], [r["passes"] for r in rows], "o-", label=name)
    axes[2].invert_xaxis()
    axes[2].set_xlabel("error threshold T")
    axes[2].set_ylabel("passes to converge")
    axes[2].set_title("termination (Table 6.2)")
    axes[2].legend(fontsize=7)
    for name, rows in result["termination_batch_8"].items():
        if rows:
            axes[3].loglog([r["threshold"] for r in rows], [r["actual"] for r in rows], "o-", label=name)
    lims = [min(r["threshold"] for rows in result["termination"].values() for r in rows),
            max(r["threshold"] for rows in result["termination"].values() for r in rows)]
    axes[3].loglog(lims, lims, "k:", label="actual = T")
    axes[3].invert_xaxis()
    axes[3].set_xlabel("error threshold T")
    axes[3].set_ylabel("actual average relative error at termination")
    axes[3].set_title("actual error at termination, batches of 8")
    axes[3].legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, "error_estimation")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--full", action="store_true")
    args = parser.parse_args()
    passes = [4, 8, 16, 32, 64, 128] if args.full else [4, 8, 16, 32, 64]
    result = {
        "overhead": overhead(40 if args.full else 12),
        "coverage": coverage(passes, [0.0, 1.0, 1.25, 1.5, 2.0]),
        "termination": termination([0.4, 0.2, 0.1, 0.05, 0.025], 4000 if args.full else 1500),
        "termination_batch_8": termination([0.4, 0.2, 0.1, 0.05, 0.025], 4000 if args.full else 1500, batch=8),
        "bias_significance": ee.BIAS_SIGNIFICANCE,
    }
    for rows in [*result["termination"].values(), *result["termination_batch_8"].values()]:
        for prev, cur in pairwise(rows):
            cur["passes_ratio_to_previous"] = cur["passes"] / prev["passes"]
    write_json("error_estimation", result)
    chart(result)
    o = result["overhead"]
    print(f"per pass: gather {1000 * o['gather_without']:.1f} ms without the error sums, "
          f"{1000 * o['gather_with']:.1f} ms with; host estimate {1000 * o['host_estimate']:.2f} ms; "
          f"pass {1000 * o['wall_without']:.0f} ms: overhead {100 * o['overhead_fraction']:.1f}%")
    for key in ("termination", "termination_batch_8"):
        print(f"{key}: threshold, passes, estimated and actual average relative error at termination")
        for name, rows in result[key].items():
            print(f"  {name}:", ", ".join(f"T {r['threshold']}: {r['passes']} passes, estimated {r['estimated']:.4f}, "
                                         f"actual {r['actual']:.4f}" for r in rows))


if __name__ == "__main__":
    main()
