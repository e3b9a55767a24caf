"""Accuracy against analytic answers and Mitsuba 3, where bounded paths, concave corners
and edges could bias the image:

- depth: a point light in a closed diffuse sphere of albedo 0.5 to 0.99, image mean over
  the analytic radiance, with paths capped at 16 bounces and ended by Russian
  roulette alone (the default, kernels/contract.py MAX_BOUNCES);
- corners: the Cornell box's concave corners against Mitsuba's path tracer
  (bench/reference/cornell-box-corners-96x96.exr), mean over the pixels within 10, 20 and
  30 (of 555) of a perpendicular wall;
- coverage split: the share of 90% bounds at least the actual error, at edge and smooth
  pixels, from 16 to 256 passes, with and without the discontinuity bias of
  worker/error_estimate.py, on a spot light's cone edge (analytic), a hard shadow (a black
  sphere over a plane under a point light, analytic) and the Cornell box's corners
  (Mitsuba). Edge pixels: within 1 pixel of a jump of a quarter in the reference
  (tests/analytic.py, edge_pixels); in the Cornell box, the pixels within 20 of a concave
  corner (its walls meet without a jump).

    python -m bench.accuracy [--full]

Writes bench/out/accuracy.json and .png.
"""

from __future__ import annotations

import argparse
import json
import tempfile
from collections.abc import Callable
from pathlib import Path

import numpy as np

import worker.error_estimate as ee
from bench.common import BENCH_DIR, bench_engine, save_figure, write_json
from kernels.contract import LUMINANCE
from tests.analytic import (
    SHADOW,
    SPOT,
    closed_sphere_scene,
    edge_pixels,
    furnace_radiance,
    shadow_scene,
    shadowed_plane,
    spot_plane,
    spot_plane_scene,
)
from tests.test_closed_scenes import concave_corner_pixels
from worker.engine import Engine
from worker.image_io import read_image
from worker.render_loop import render
from worker.scene import load_scene_file
from worker.settings import Settings

ALBEDOS = (0.5, 0.8, 0.9, 0.95, 0.99)
CORNERS = BENCH_DIR / "reference" / "cornell-box-corners-96x96.exr"


def scene_engine(scene: dict, **settings: object) -> Engine:
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "scene.json"
        path.write_text(json.dumps(scene))
        parsed, base = load_scene_file(path)
        return Engine(parsed, base, Settings(**settings))


def depth(passes: int) -> list[dict]:
    """Image mean / analytic radiance per albedo, capped at 16 bounces and not."""
    rows = []
    for rho in ALBEDOS:
        photons = max(1 << 12, int((1 << 15) * (1 - rho) / 0.1))  # about the same photons stored per pass
        row: dict = {"albedo": rho, "photons_per_pass": photons, "passes": passes, "expected_cap_16": 1 - rho ** 16}
        for name, cap in (("cap_16", 16), ("roulette", None)):
            eng = scene_engine(closed_sphere_scene((rho,) * 3), photons_per_pass=photons, seed=21,
                               initial_radius=0.05, **({"max_bounces": cap} if cap else {}))
            st = render(eng, passes=passes)
            row[name] = float(st.radiance().mean() / furnace_radiance(rho))
        rows.append(row)
    return rows


def corners(passes: int) -> dict:
    eng = bench_engine("cornell-box", (96, 96), photons_per_pass=1 << 17, seed=13)
    img = render(eng, passes=passes).radiance().reshape(96, 96, 3)
    ref = read_image(CORNERS)[..., :3]
    out = {}
    for band in (10.0, 20.0, 30.0):
        m = concave_corner_pixels(eng, band)
        out[f"within {band:g}"] = {"pixels": int(m.sum()),
                                   "ratio_rgb": (img[m].mean(axis=0) / ref[m].mean(axis=0)).tolist()}
    return {"passes": passes, "photons_per_pass": 1 << 17, "bands": out}


Case = Callable[[], tuple[Engine, np.ndarray, np.ndarray, np.ndarray]]


def spot_case() -> tuple[Engine, np.ndarray, np.ndarray, np.ndarray]:
    eng = scene_engine(spot_plane_scene(), photons_per_pass=1 << 14, seed=31)
    truth = spot_plane(eng, **SPOT)
    return eng, truth, edge_pixels(truth.reshape(64, 64)).ravel(), np.ones(truth.shape, bool)


def shadow_case() -> tuple[Engine, np.ndarray, np.ndarray, np.ndarray]:
    eng = scene_engine(shadow_scene(), photons_per_pass=1 << 14, seed=31)
    truth = shadowed_plane(eng, **SHADOW)
    return eng, truth, edge_pixels(truth.reshape(64, 64)).ravel(), np.ones(truth.shape, bool)


def cornell_case() -> tuple[Engine, np.ndarray, np.ndarray, np.ndarray]:
    eng = bench_engine("cornell-box", (96, 96), photons_per_pass=1 << 15, seed=31)
    truth = (read_image(CORNERS)[..., :3] @ LUMINANCE).ravel()
    lamp = truth > 5.0  # the lamp seen directly: emission, not the photon estimate
    return eng, truth, concave_corner_pixels(eng, 20.0).ravel(), ~lamp


CASES: dict[str, Case] = {"spot cone edge": spot_case, "hard shadow": shadow_case, "cornell corners": cornell_case}


def coverage_split(checkpoints: list[int]) -> dict:
    out = {}
    for name, case in CASES.items():
        eng, truth, edge, valid = case()
        rows: list[dict] = []

        def observe(st: object, _: float, truth: np.ndarray = truth, edge: np.ndarray = edge,
                    valid: np.ndarray = valid, rows: list = rows) -> None:
            if st.passes not in checkpoints:
                return
            row: dict = {"passes": st.passes}
            for label, on in (("with_discontinuity_bias", True), ("without", False)):
                est = ee.estimate(st, 0.9, discontinuities=on)
                covered = est.bound >= np.abs(est.luminance - truth)
                use = est.known & valid
                row[label] = {"edge": float(covered[use & edge].mean()), "smooth": float(covered[use & ~edge].mean()),
                              "all": float(covered[use].mean())}
                if on:
                    row["edge_pixels"], row["smooth_pixels"] = int((use & edge).sum()), int((use & ~edge).sum())
                    row["estimated_average"] = est.average
                    row["actual_average"] = ee.actual_average(est, np.where(valid, truth, est.luminance))
            rows.append(row)

        render(eng, passes=max(checkpoints), progress=observe)
        out[name] = rows
    return out


def chart(result: dict) -> None:
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(17, 4.6))
    rows = result["depth"]
    for key, style in (("cap_16", "s--"), ("roulette", "o-")):
        axes[0].plot([r["albedo"] for r in rows], [r[key] for r in rows], style, label=key.replace("_", " "))
    axes[0].plot([r["albedo"] for r in rows], [r["expected_cap_16"] for r in rows], "k:", label="1 - rho^16")
    axes[0].set_xlabel("albedo of the closed sphere")
    axes[0].set_ylabel("image mean / analytic")
    axes[0].set_title("depth: energy against albedo")
    axes[0].legend(fontsize=8)
    for (name, rows), colour in zip(result["coverage_split"].items(), ("C0", "C1", "C2"), strict=False):
        p = [r["passes"] for r in rows]
        axes[1].semilogx(p, [r["with_discontinuity_bias"]["edge"] for r in rows], "o-", color=colour, label=f"{name}")
        axes[1].semilogx(p, [r["without"]["edge"] for r in rows], "x:", color=colour, label=f"{name}, before")
        axes[2].semilogx(p, [r["with_discontinuity_bias"]["smooth"] for r in rows], "o-", color=colour, label=name)
        axes[2].semilogx(p, [r["without"]["smooth"] for r in rows], "x:", color=colour, label=f"{name}, before")
    for ax, what in ((axes[1], "edge"), (axes[2], "smooth")):
        ax.axhspan(0.8, 1.0, color="grey", alpha=0.15)
        ax.axhline(0.9, color="k", lw=0.8)
        ax.set_xlabel("passes")
        ax.set_ylabel("share of 90% bounds >= actual error")
        ax.set_title(f"coverage at {what} pixels (band: within 10 points)")
        ax.legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, "accuracy")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--full", action="store_true")
    args = parser.parse_args()
    result = {
        "depth": depth(16 if args.full else 8),
        "corners": corners(48 if args.full else 24),
        "coverage_split": coverage_split([16, 32, 64, 128, 256]),
    }
    write_json("accuracy", result)
    chart(result)
    for r in result["depth"]:
        print(f"albedo {r['albedo']}: mean/analytic {r['cap_16']:.4f} at 16 bounces "
              f"(1 - rho^16 = {r['expected_cap_16']:.4f}), {r['roulette']:.4f} by Russian roulette alone")
    for band, r in result["corners"]["bands"].items():
        print(f"corners {band}: {r['pixels']} pixels, ours / Mitsuba {np.round(r['ratio_rgb'], 4).tolist()}")
    for name, rows in result["coverage_split"].items():
        for r in rows:
            w, o = r["with_discontinuity_bias"], r["without"]
            print(f"{name} @ {r['passes']}: edge {w['edge']:.3f} (before {o['edge']:.3f}, {r['edge_pixels']} px), "
                  f"smooth {w['smooth']:.3f} (before {o['smooth']:.3f}), all {w['all']:.3f} (before {o['all']:.3f}); "
                  f"average estimated {r['estimated_average']:.4f}, actual {r['actual_average']:.4f}")


if __name__ == "__main__":
    main()
