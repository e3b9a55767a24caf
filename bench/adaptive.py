"""Adaptive photon tracing (`sampler: adaptive`) against uniform photon tracing, one run:

1. the visible fraction V_c (and the visible-photon ratio 1 / V_c, the paper's Table 1
   column), the final mutation size theta and the achieved acceptance of chains in every
   pass (`sampler: adaptive`), per bundled scene
   and per zoom level of `directional-caustic` (the camera closing in on the caustic,
   vertical field of view 40 (the scene's), 20, 10, 5, 2.5 and 1.25 degrees);
2. error against time, uniform and `sampler: auto` on the same scene and budget (SPPM, exact
   gather), with a chart per scene; the clock is this process's CPU seconds (set-up and
   rendering), the runs taking turns pass by pass. Two seeds per sampler, paired
   (a seed's initial radius comes from its own uniform probe pass, the same for both
   samplers; on the zoom levels it moves the radius, and so the error, from seed to seed,
   so one seed's ratio says little): the error is the two runs' mean, split into
   noise (the relative RMS of their difference over sqrt 2, one image's) and bias (what
   the mean image's error keeps beyond its noise, sqrt(e_mean^2 - noise^2 / 2));
3. error at equal passes: uniform and chains in every pass, the same passes of the same photons per pass (a
   chain pass runs adaptive.iterations; `traced` counts its paths, starts included), with
   the CPU seconds each took; and the
   noise alone, from a second seed (the relative RMS of the two images' difference over
   sqrt 2), which needs no reference: at equal passes both samplers shrink the radius
   alike (a chain pass's sums are in uniform photons), so this ratio is the chains' gain itself.

4. (`--defaults`, alone) at the service's defaults (256 pixels, 2^18 photons a pass, 12 CPU
   s): uniform, auto and chains in every pass,
   on cornell-box, gap, directional-caustic at fov 5 and 1.25 and a point-lit patch
   (tests/analytic.py patch_scene) at fov 6, 2 and 0.6 (V_c falling with the field of
   view): the noise of two seeds (no reference needed at this size) and, on the patch,
   the error against its closed form, and what auto chose.
5. (`--bound`, alone) the most any sampler of F = V / V_c could gain at equal time, from a
   uniform pass's own stage times (device seconds) and V_c: such a sampler's visible paths
   are distributed as uniform tracing's visible ones, so at equal visible paths it leaves
   the eye pass, the gather and the visible paths' trace and build as they are. An ideal one
   (invisible paths free) takes T - (1 - V_c)(trace + build) a pass; the paper's kernel (a
   traced path finds a new visible one gain x V_c times as often as uniform tracing,
   new_visible_gain; only visible paths stored), with free visibility tests and independent
   samples, T - trace (1 - 1 / gain) - build (1 - V_c). A time gain X lowers the error at
   most by sqrt(X) (all of it noise; SPPM's shrinking radius gives less), so 2x needs X >= 4.

6. (`--closed`, alone) `sampler: auto` against uniform photons and chains in every pass, at
   equal CPU time (`--closed-seconds`, 12 by default), two seeds each, 64 pixels, the
   service's 2^18 photons a pass (`--closed-photons`), on the closed scenes `window-sky` (lit by the sky through
   a window), `slit-room` (lit through a slit) and, where auto should keep uniform photons,
   `cornell-box`; and uniform photons at smaller passes (`--closed-uniform-photons`, 2^17
   and 2^15: a chain pass costs less than a uniform pass of 2^18 photons, and more passes
   alone can lower the error): the error against a reference where bench/reference holds
   one (window-sky's Mitsuba path-traced one, cornell-box's), else the noise of the two
   seeds; auto's choice and figures per seed; the load average before and after.

Per scene, part 1 also gives the new visible paths per traced path (visible uniform draws
plus accepted mutations): a uniform tracer's is V_c. A chain's other splats count a state
again; they add no new path, so when this is not well above V_c the chains cannot win.

    python -m bench.adaptive [--full] [--smoke] [--visibility-only] [--reference-seconds S] [--photons-per-pass P]
        [--equal-paths-passes N] [--defaults] [--bound] [--closed [--closed-seconds S]]

Error: the relative RMS of bench/error_vs_time.py against its cached references
(bench/reference/<scene>-<W>x<H>.exr); the zoom levels get their own references (two
long uniform SPPM runs, as bench/make_reference.py makes them) on first use. `--smoke`
runs everything tiny (a few seconds a scene) to check the script, its figures mean nothing.
Writes bench/out/adaptive.json and bench/out/adaptive_<scene>.png (with --smoke,
adaptive-smoke*); part 4 adaptive_defaults.json and .png, part 5 adaptive_bound.json, part 6
adaptive_closed.json (adaptive_closed_<P>.json with other photons a pass).
Timing figures need a quiet machine.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from bench.common import BENCH_DIR, save_figure, write_json
from bench.error_vs_time import REFERENCES, SCENES, reference_path, rel_rms, resolution
from tests.analytic import patch_plane, patch_scene
from worker import adaptive
from worker.engine import Engine
from worker.image_io import read_image, write_image
from worker.render_loop import render
from worker.scene import Scene, bundled_scene_path, load_scene_file
from worker.settings import DEFAULTS, Settings

BUNDLED = ("cornell-box", "cornell-caustics", "directional-caustic", "furnace", "gap", "glossy", "point-plane",
           "smallppm", "window-sky")
ZOOM_SCENE = "directional-caustic"
ZOOM_FOVS = (40.0, 20.0, 10.0, 5.0, 2.5, 1.25)  # degrees; 40 is the scene's own view
CAUSTIC = (0.225, 0.0, 0.175)  # where the light's ray through the glass sphere's centre meets the ground
# Photons per pass, both samplers. SPPM's radius falls by pass, not by photon, so on a
# zoomed caustic the error at a given number of traced paths is mostly the radius's bias
# unless passes are many: small passes, so that a budget runs many of them.
PHOTONS = 1 << 13
SEED = 7
VARIANTS = {"uniform": "uniform", "auto": "auto", "chains": "adaptive"}  # the sampler each runs


def zoomed(fov: float) -> Scene:
    """`directional-caustic` with the camera turned to the caustic and its view narrowed to
    `fov` degrees (the scene itself at its own 40)."""
    parsed, _ = load_scene_file(bundled_scene_path(ZOOM_SCENE))
    if fov == parsed.camera.fov:
        return parsed
    return parsed.model_copy(update={"camera": parsed.camera.model_copy(update={"fov": fov, "look_at": CAUSTIC})})


def engine(scene: Scene, res: tuple[int, int], photons: int, seed: int = SEED, **settings: object) -> Engine:
    _, base = load_scene_file(bundled_scene_path(ZOOM_SCENE))  # bundled scenes share one folder
    return Engine(scene, base, Settings(resolution=res, photons_per_pass=photons, seed=seed, **settings))


def visibility(scene: Scene, res: tuple[int, int], photons: int, passes: int) -> dict[str, float]:
    """V_c, theta and the acceptance after `passes` passes of chains (the last half's
    acceptance), and the gain of the chains' kernel (new_visible_gain)."""
    eng = engine(scene, res, photons, sampler="adaptive")
    state = render(eng, passes=passes // 2)
    half = dict(state.counters)
    render(eng, passes=passes, state=state)
    c = state.counters
    mutations = c["mutations"] - half["mutations"]
    v_c = adaptive.visible_fraction(c)
    traced = c["draws"] + c["mutations"] + c.get("boot", 0)
    return {"visible_fraction": v_c, "visible_photon_ratio": 1.0 / v_c if v_c else None,
            "traced_per_splat": traced / c["splats"] if c["splats"] else None,
            "new_visible_per_traced": (c["visible"] + c["accepted"]) / traced if traced else None,
            "theta": adaptive.theta(c, eng.settings.target_acceptance),
            "acceptance": (c["accepted"] - half["accepted"]) / mutations if mutations else None, "passes": passes,
            "gain": new_visible_gain(v_c, eng.settings.target_acceptance) if v_c is not None else None}


def new_visible_gain(v_c: float, target: float) -> float:
    """The chains' new visible paths per traced path over uniform tracing's (V_c). A chain
    iteration traces a uniform draw and, when it is invisible, a mutation; it finds a new
    visible path with probability V_c + (1 - V_c) A, A the acceptance (held at the target),
    so per traced path (V_c + (1 - V_c) A) / (2 - V_c), against V_c for uniform tracing."""
    if v_c <= 0.0:
        return math.inf
    return (v_c + (1.0 - v_c) * target) / ((2.0 - v_c) * v_c)


def warmed(scene: Scene, res: tuple[int, int], photons: int, sampler: str, seed: int = SEED) -> Engine:
    """An engine whose kernels have run once (two passes of a state thrown away, a uniform
    and, but with sampler uniform, a chain one): PoCL compiles a kernel at its first launch
    in a context (seconds, unless its disk cache has it), which is no sampler's cost."""
    eng = engine(scene, res, photons, seed=seed, sampler=sampler)
    render(eng, passes=2)
    return eng


def take_turns(scene: Scene, res: tuple[int, int], photons: int, budget: float, keys: list[tuple[str, int]],
               after_pass: Callable[[dict], None] | None = None) -> dict[tuple[str, int], dict]:
    """Per (variant of VARIANTS, seed) a run (engine, state, CPU seconds spent), rendered
    pass by pass in turn until each has spent `budget`, each on its own clock (set-up and
    rendering, not the kernels' compilation), so that a shared machine's load, which moves
    a pass's CPU time between runs made one after the other, falls on all of them alike.
    `after_pass(run)` is called after each pass, off the clock."""
    runs = {}
    for variant, seed in keys:
        sampler, own_photons = sampler_photons(variant, photons)
        eng = warmed(scene, res, own_photons, sampler, seed)
        t0 = time.process_time()
        runs[(variant, seed)] = {"engine": eng, "state": eng.start()}
        runs[(variant, seed)]["spent"] = time.process_time() - t0
    while any(run["spent"] < budget for run in runs.values()):
        for run in runs.values():
            if run["spent"] < budget:
                t0 = time.process_time()
                render(run["engine"], passes=run["state"].passes + 1, state=run["state"])
                run["spent"] += time.process_time() - t0
                if after_pass is not None:
                    after_pass(run)
    return runs


def sampler_photons(variant: str, photons: int) -> tuple[str, int]:
    """A variant's sampler and photons a pass: VARIANTS[variant] at `photons`, or for
    `uniform@P` uniform photons at P a pass."""
    name, _, own = variant.partition("@")
    return VARIANTS[name], int(own) if own else photons


def curves(scene: Scene, res: tuple[int, int], ref: np.ndarray, photons: int, budget: float,
           keys: list[tuple[str, int]]) -> dict[tuple[str, int], tuple[list, np.ndarray, int]]:
    """Per (sampler, seed): (CPU seconds, relative RMS error) after every pass, the final
    image and its passes (take_turns)."""
    def image(run: dict) -> np.ndarray:
        return run["engine"].integrator.image(run["state"]).reshape(res[1], res[0], 3)

    def record(run: dict) -> None:
        run.setdefault("points", []).append((run["spent"], rel_rms(image(run), ref)))

    runs = take_turns(scene, res, photons, budget, keys, record)
    return {key: (run.get("points", []), image(run), run["state"].passes) for key, run in runs.items()}


def split(a: np.ndarray, b: np.ndarray, ref: np.ndarray) -> dict[str, float]:
    """Two seeds' images: their mean error, one image's noise and the bias (module docstring)."""
    noise = rel_rms(a, b) / math.sqrt(2.0)
    mean_error = rel_rms(0.5 * (a + b), ref)
    return {"error": 0.5 * (rel_rms(a, ref) + rel_rms(b, ref)), "noise": noise,
            "bias": math.sqrt(max(mean_error ** 2 - noise ** 2 / 2.0, 0.0))}


def traced_paths(counters: dict[str, int], passes: int, photons: int) -> int:
    """Photon paths a run traced: a uniform sampler's passes trace `photons` each; the
    chains' (sampler adaptive, every pass) their draws, mutations and starts."""
    if "draws" not in counters:
        return passes * photons
    return counters["draws"] + counters.get("mutations", 0) + counters.get("boot", 0)


def equal_paths(scene: Scene, res: tuple[int, int], ref: np.ndarray, photons: int, passes: int) -> dict:
    """Both samplers, `passes` passes of `photons` photon paths: error, CPU seconds, paths traced."""
    out = {}
    for sampler in ("uniform", "adaptive"):
        eng = warmed(scene, res, photons, sampler)
        t0 = time.process_time()
        state = render(eng, passes=passes)
        seconds = time.process_time() - t0
        c = state.counters
        img = eng.integrator.image(state).reshape(res[1], res[0], 3)
        other = engine(scene, res, photons, sampler=sampler, seed=SEED + 1)
        twin = other.integrator.image(render(other, passes=passes)).reshape(res[1], res[0], 3)
        out[sampler] = {"error": rel_rms(img, ref), "noise": rel_rms(img, twin) / math.sqrt(2.0),
                        "cpu_seconds": seconds,
                        "traced": traced_paths(c, passes, photons)}
    out["uniform_over_adaptive"] = out["uniform"]["error"] / out["adaptive"]["error"]
    out["noise_uniform_over_adaptive"] = out["uniform"]["noise"] / out["adaptive"]["noise"]
    return out


def zoom_reference(fov: float, res: tuple[int, int], photons: int, seconds: float, folder: Path) -> np.ndarray:
    """Two uniform SPPM runs of `seconds`, averaged (cached in `folder`)."""
    path = folder / f"{ZOOM_SCENE}-fov{fov:g}-{res[0]}x{res[1]}.exr"
    if not path.exists():
        runs = []
        for seed in (101, 102):
            eng = Engine(zoomed(fov), load_scene_file(bundled_scene_path(ZOOM_SCENE))[1],
                         Settings(resolution=res, photons_per_pass=photons, seed=seed))
            st = render(eng, seconds=seconds)
            runs.append((st.radiance().reshape(res[1], res[0], 3), st.passes))
        (a, pa), (b, pb) = runs
        write_image(path, 0.5 * (a + b))
        path.with_suffix(".json").write_text(json.dumps({
            "scene": ZOOM_SCENE, "fov": fov, "look_at": CAUSTIC, "resolution": list(res),
            "method": "sppm (photonfarm, exact gather, uniform photons)", "passes": [pa, pb], "seconds": seconds,
            "own_relative_rms_error": rel_rms(a, b) / 2}, indent=1))
    return read_image(path)[..., :3].astype(np.float64)


DEFAULTS_SIDE, DEFAULTS_PHOTONS, DEFAULTS_BUDGET = 256, 1 << 18, 12.0
PATCH_FOVS = (6.0, 2.0, 0.6)


def at_defaults(scene: Scene, res: tuple[int, int], photons: int, budget: float, analytic: bool) -> dict:
    """Uniform, adaptive and always-mutating chains, two seeds each, taking turns pass by
    pass on their own CPU clocks: passes, noise (two seeds' relative RMS difference over
    sqrt 2), V_c and, where `analytic` (the patch), the error against patch_plane."""
    keys = [(variant, seed) for variant in VARIANTS for seed in (SEED, SEED + 1)]
    runs = take_turns(scene, res, photons, budget, keys)
    out = {}
    for variant in VARIANTS:
        pair = [runs[(variant, seed)] for seed in (SEED, SEED + 1)]
        images = [run["engine"].integrator.image(run["state"]).reshape(res[1], res[0], 3) for run in pair]
        counters = pair[0]["state"].counters
        out[variant] = {"passes": [run["state"].passes for run in pair],
                        "noise": rel_rms(images[0], images[1]) / math.sqrt(2.0),
                        "visible_fraction": adaptive.visible_fraction(counters) if counters else None,
                        "theta": adaptive.theta(counters, DEFAULTS.target_acceptance) if counters else None}
        if analytic:
            truth = patch_plane(pair[0]["engine"]).reshape(res[1], res[0])
            out[variant]["error"] = [float(np.sqrt(np.mean((img.mean(axis=2) / truth - 1.0) ** 2))) for img in images]
    v_c = out["chains"]["visible_fraction"]
    out["gain"] = new_visible_gain(v_c, Settings.model_fields["target_acceptance"].default) if v_c is not None else None
    auto = adaptive.choice(pair_of(runs, "auto")[0]["state"].counters, photons)
    out["auto_choice"] = None if auto is None else {"chains": auto.chains, "ratio": auto.ratio}
    return out


def pair_of(runs: dict, variant: str) -> list[dict]:
    return [runs[(variant, seed)] for seed in (SEED, SEED + 1)]


def defaults_chart(report: dict, prefix: str) -> None:
    import matplotlib.pyplot as plt

    names = list(report)
    fig, ax = plt.subplots(figsize=(7.5, 4.4))
    for k, variant in enumerate(("auto", "chains")):
        ratios = [report[n]["uniform"]["noise"] / report[n][variant]["noise"] for n in names]
        ax.bar(np.arange(len(names)) + 0.4 * k - 0.2, ratios, 0.4, label=variant)
    ax.axhline(1.0, color="k", lw=0.8)
    labels = [f"{n.replace(ZOOM_SCENE, 'caustic')}\ngain {report[n]['gain']:.3g}" for n in names]
    ax.set_xticks(np.arange(len(names)), labels, fontsize=7)
    ax.set_ylabel("noise, uniform / sampler (above 1: sampler wins)")
    ax.set_title(f"{DEFAULTS_SIDE} px, 2^18 photons a pass, {DEFAULTS_BUDGET:g} CPU s")
    ax.legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, f"{prefix}_defaults")


def defaults(smoke: bool) -> None:
    """Part 4 (module docstring): bench/out/adaptive_defaults.json and .png."""
    side, photons, budget, prefix = (DEFAULTS_SIDE, DEFAULTS_PHOTONS, DEFAULTS_BUDGET, "adaptive")
    if smoke:
        side, photons, budget, prefix = 32, 1 << 12, 0.5, "adaptive-smoke"
    cases = {name: (load_scene_file(bundled_scene_path(name))[0], resolution(name, side), False)
             for name in ("cornell-box", "gap")}
    cases.update({f"{ZOOM_SCENE} fov {fov:g}": (zoomed(fov), resolution(ZOOM_SCENE, side), False)
                  for fov in (5.0, 1.25)})
    cases.update({f"patch fov {fov:g}": (Scene.model_validate(patch_scene(fov)), (side, side), True)
                  for fov in PATCH_FOVS})
    report = {}
    for name, (scene, res, analytic) in cases.items():
        report[name] = at_defaults(scene, res, photons, budget, analytic)
        print(name, report[name], flush=True)
    write_json(prefix + "_defaults", {"measured": time.strftime("%Y-%m-%d %H:%M:%S"), "resolution_side": side,
                                      "photons_per_pass": photons, "budget_cpu_seconds": budget, "cases": report})
    defaults_chart(report, prefix)


BOUND_SIDES = (64, 128, 256)
BOUND_PASSES = 4  # timed passes, after 2 (the probe's and the kernels' first launch)


def stage_bound(scene: Scene, res: tuple[int, int], photons: int, passes: int) -> dict:
    """Part 5 (module docstring) for one case: a uniform pass's device seconds by stage, V_c
    (from as many chain passes, untimed) and the two time bounds."""
    eng = engine(scene, res, photons, sampler="uniform")
    times = eng.device.times
    state = render(eng, passes=2)
    times.settle()
    times.seconds.clear()
    render(eng, passes=2 + passes, state=state)
    times.settle()
    stage = {k: v / passes for k, v in times.seconds.items()}
    total, trace, build = sum(stage.values()), stage["trace"], stage["build"]
    v_c = adaptive.visible_fraction(render(engine(scene, res, photons, sampler="adaptive"), passes=passes).counters)
    if v_c is None:
        raise ValueError("the chain passes drew no uniform path")
    gain = new_visible_gain(v_c, Settings.model_fields["target_acceptance"].default)
    ideal = total / (total - (1.0 - v_c) * (trace + build))
    chains = total / (total - trace * max(0.0, 1.0 - 1.0 / gain) - build * (1.0 - v_c))
    return {"resolution": list(res), "stage_seconds": stage, "pass_seconds": total, "visible_fraction": v_c,
            "gain": gain, "time_gain_ideal": ideal, "time_gain_chains": chains,
            "error_gain_ideal": math.sqrt(ideal), "error_gain_chains": math.sqrt(chains)}


def bound(smoke: bool) -> None:
    """Part 5: bench/out/adaptive_bound.json."""
    sides, photons, passes, prefix = BOUND_SIDES, DEFAULTS_PHOTONS, BOUND_PASSES, "adaptive"
    if smoke:
        sides, photons, passes, prefix = (32,), 1 << 12, 1, "adaptive-smoke"
    cases = {name: load_scene_file(bundled_scene_path(name))[0] for name in ("gap", "cornell-box")}
    cases.update({f"{ZOOM_SCENE} fov {fov:g}": zoomed(fov) for fov in (5.0, 1.25)})
    report: dict = {}
    for name, scene in cases.items():
        for side in sides:
            res = resolution(ZOOM_SCENE if name.startswith(ZOOM_SCENE) else name, side)
            row = stage_bound(scene, res, photons, passes)
            report[f"{name} {side}"] = row
            print(f"{name} {side} px: pass {row['pass_seconds']:.3f} s, V_c {row['visible_fraction']:.3f}, gain "
                  f"{row['gain']:.2f}; time gain at most {row['time_gain_ideal']:.2f} (ideal), "
                  f"{row['time_gain_chains']:.2f} (the chains); error gain at most {row['error_gain_ideal']:.2f}, "
                  f"{row['error_gain_chains']:.2f}", flush=True)
    write_json(prefix + "_bound", {"measured": time.strftime("%Y-%m-%d %H:%M:%S"), "photons_per_pass": photons,
                                   "timed_passes": passes, "cases": report})


def chart(name: str, curves: dict[str, list], v_c: float | None, prefix: str) -> None:
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.4))
    for sampler, points in curves.items():
        if points:
            ax.loglog(*zip(*points, strict=True), "-", ms=3, label=sampler)
    ax.set_xlabel("CPU time, s")
    ax.set_ylabel("relative RMS error")
    ax.set_title(f"{name}: adaptive vs uniform photons (V_c {v_c:.3g})" if v_c else name)
    ax.legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, f"{prefix}_{name}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--full", action="store_true", help="128-pixel images, 60 s per sampler and scene")
    parser.add_argument("--smoke", action="store_true", help="tiny run: checks the script, measures nothing")
    parser.add_argument("--reference-seconds", type=float, default=120.0, help="per run, for the zoom references")
    parser.add_argument("--visibility-only", action="store_true", help="part 1 alone (no timing)")
    parser.add_argument("--photons-per-pass", type=int, default=PHOTONS)
    parser.add_argument("--equal-paths-passes", type=int, default=64, help="part 3: passes per sampler")
    parser.add_argument("--only", nargs="*", help="cases of parts 2 and 3 to run (default: all)")
    parser.add_argument("--defaults", action="store_true", help="part 4 alone: the service's defaults")
    parser.add_argument("--bound", action="store_true", help="part 5 alone: the most a sampler of V could gain")
    parser.add_argument("--closed", action="store_true", help="part 6 alone: sampler auto on closed scenes")
    parser.add_argument("--closed-seconds", type=float, default=12.0, help="part 6: CPU seconds per run")
    parser.add_argument("--closed-photons", type=int, default=DEFAULTS_PHOTONS, help="part 6: photons per pass")
    parser.add_argument("--closed-uniform-photons", type=int, nargs="*", default=[1 << 17, 1 << 15],
                        help="part 6: uniform photons at these photons per pass too (uniform@P)")
    args = parser.parse_args()
    if args.defaults:
        defaults(args.smoke)
        return
    if args.bound:
        bound(args.smoke)
        return
    if args.closed:
        closed(args)
        return
    side, budget, passes = (128, 60.0, 16) if args.full else (64, 12.0, 8)
    photons = args.photons_per_pass
    ref_seconds, references, prefix = args.reference_seconds, REFERENCES, "adaptive"
    if args.smoke:  # outputs apart from the real ones, references thrown away
        side, budget, photons, passes, ref_seconds = 64, 1.0, 1 << 12, 4, 1.0
        references, prefix = Path(tempfile.mkdtemp(prefix="adaptive-smoke-")), "adaptive-smoke"
    if args.smoke:
        args.equal_paths_passes = 2
    report: dict = {"measured": time.strftime("%Y-%m-%d %H:%M:%S"), "budget_cpu_seconds": budget,
                    "photons_per_pass": photons, "smoke": args.smoke, "visibility": {}, "equal_time": {},
                    "equal_paths": {}}
    # 1. V_c per bundled scene and zoom level.
    for name in BUNDLED:
        parsed, _ = load_scene_file(bundled_scene_path(name))
        report["visibility"][name] = visibility(parsed, resolution(name, side), photons, passes)
        print(name, report["visibility"][name], flush=True)
    for fov in ZOOM_FOVS[1:]:
        key = f"{ZOOM_SCENE} fov {fov:g}"
        report["visibility"][key] = visibility(zoomed(fov), resolution(ZOOM_SCENE, side), photons, passes)
        print(key, report["visibility"][key], flush=True)
    if args.visibility_only:
        write_json(prefix + "-visibility", report)
        return
    # 2. Equal time, uniform and adaptive, where a reference exists (the zoom levels make theirs).
    cases = {name: (load_scene_file(bundled_scene_path(name))[0], None) for name in SCENES}
    cases.update({f"{ZOOM_SCENE} fov {fov:g}": (zoomed(fov), fov) for fov in ZOOM_FOVS[1:]})
    for name, (scene, fov) in cases.items():
        if args.only and name not in args.only:
            continue
        res = resolution(ZOOM_SCENE if fov else name, side)
        if fov is None:
            path = reference_path(name, res)
            if not path.exists():
                print(f"{name}: no reference {path.relative_to(BENCH_DIR)} (python -m bench.error_vs_time "
                      "--make-references), skipped", flush=True)
                continue
            ref = read_image(path)[..., :3].astype(np.float64)
        else:
            ref = zoom_reference(fov, res, photons, ref_seconds, references)
        v_c = report["visibility"].get(name, {}).get("visible_fraction")
        report["equal_time"][name], report["equal_paths"][name] = compare(
            name, scene, res, ref, photons, budget, v_c, prefix, args.equal_paths_passes)
    write_json(prefix, report)


def compare(name: str, scene: Scene, res: tuple[int, int], ref: np.ndarray, photons: int, budget: float,
            v_c: float | None, prefix: str, paths_passes: int,
            variants: tuple[str, ...] = ("uniform", "auto")) -> tuple[dict, dict]:
    """Parts 2 and 3 for one case: equal time (two seeds for each of `variants` of VARIANTS,
    charted) and equal paths."""
    runs = curves(scene, res, ref, photons, budget,
                  [(variant, seed) for variant in variants for seed in (SEED, SEED + 1)])
    series = {variant: runs[(variant, SEED)][0] for variant in variants}
    splits: dict[str, dict] = {variant: {**split(runs[(variant, SEED)][1], runs[(variant, SEED + 1)][1], ref),
                                         "passes": [runs[(variant, seed)][2] for seed in (SEED, SEED + 1)]}
                               for variant in variants}
    equal_time = {"resolution": list(res), "seeds": [SEED, SEED + 1], "split": splits,
                  **{f"uniform_over_{v}": splits["uniform"]["error"] / splits[v]["error"] for v in variants[1:]},
                  "curves": series}
    chart(name.replace(" ", "-"), series, v_c, prefix)
    print(name, splits, flush=True)
    same_paths = equal_paths(scene, res, ref, photons, paths_passes)
    print(name, "equal paths", same_paths, flush=True)
    return equal_time, same_paths


CLOSED_SCENES = ("window-sky", "slit-room", "cornell-box")


def closed(args: argparse.Namespace) -> None:
    """Part 6 (module docstring): bench/out/adaptive_closed.json."""
    side, budget, photons, prefix = 64, args.closed_seconds, args.closed_photons, "adaptive"
    if args.smoke:
        side, budget, photons, prefix = 32, 1.0, 1 << 12, "adaptive-smoke"
    report: dict = {"measured": time.strftime("%Y-%m-%d %H:%M:%S"), "budget_cpu_seconds": budget,
                    "photons_per_pass": photons, "smoke": args.smoke, "cases": {}}
    for name in CLOSED_SCENES:
        scene = load_scene_file(bundled_scene_path(name))[0]
        res = resolution(name, side)
        path = reference_path(name, res)
        ref = read_image(path)[..., :3].astype(np.float64) if path.exists() and not args.smoke else None
        load = os.getloadavg()
        variants = [*VARIANTS, *(f"uniform@{p}" for p in args.closed_uniform_photons)]
        runs = take_turns(scene, res, photons, budget, [(v, seed) for v in variants for seed in (SEED, SEED + 1)])
        case: dict = {"resolution": list(res), "reference": path.name if ref is not None else None,
                      "load_average_before_after": [load, os.getloadavg()]}
        for variant in variants:
            pair = pair_of(runs, variant)
            a, b = (run["engine"].integrator.image(run["state"]).reshape(res[1], res[0], 3) for run in pair)
            case[variant] = {"passes": [run["state"].passes for run in pair],
                             **(split(a, b, ref) if ref is not None else {"noise": rel_rms(a, b) / math.sqrt(2.0)})}
        choices = [adaptive.choice(run["state"].counters, photons) for run in pair_of(runs, "auto")]
        case["auto_choice"] = [None if c is None else {"chains": c.chains, "ratio": c.ratio, "note": c.note()}
                               for c in choices]
        report["cases"][name] = case
        print(name, json.dumps(case, indent=1), flush=True)
    write_json(f"{prefix}_closed" + ("" if photons == DEFAULTS_PHOTONS else f"_{photons}"), report)


if __name__ == "__main__":
    main()
