"""Peer comparison: how long we take to reach the image error of smallppm's 4M photon paths.

smallppm (Hachisuka's C++ reference, measured once and recorded in bench/peers.json)
traces 4M photon paths of its scene on this machine's cores; its image's error is the
display-space RMS (bench.common) against bench/reference/smallppm-ref.exr. Here the
engine renders the same scene from the same camera (SPPM, stochastic gather, alpha 0.7,
default settings), and after every pass its image is compared with the same reference
(box-filtered 2x2 first if the reference is half resolution). The clock counts engine
set-up (context, program, initial radius) and every run_batch + merge; the per-pass
error evaluation is not counted. It stops at smallppm's error or at 3x smallppm's time.

Reported: our time to reach smallppm's error, smallppm's time, and the speed ratio
smallppm_time / our_time (the goal is >= 5). When the cap comes first, the error at
smallppm's time and a power-law extrapolation (fit over the last half of the curve) of
the time to reach the target are reported instead. photons_per_pass defaults to the
engine's; --sweep runs each of CANDIDATES (2^18, 2^19 and 2^20 photons per pass).

    python -m bench.peer_smallppm [--photons-per-pass N | --sweep] [--peer-image image.ppm]
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import asdict, dataclass, field

import numpy as np

from bench.common import (
    PEERS_FILE,
    REFERENCE_FILE,
    bench_engine,
    box2x2,
    display,
    display_rms,
    read_ppm,
    save_figure,
    write_json,
)
from worker.image_io import read_image
from worker.render_loop import render
from worker.settings import DEFAULTS

CANDIDATES = (1 << 18, 1 << 19, 1 << 20)
CAP_FACTOR = 3.0  # give up at this multiple of smallppm's time
GOAL_RATIO = 5.0


@dataclass
class Run:
    photons_per_pass: int
    gather: str
    setup_seconds: float
    reached: bool = False
    seconds_to_reach: float | None = None  # render clock, set-up included
    paths_to_reach: int | None = None
    ratio: float | None = None  # smallppm seconds / seconds_to_reach
    final_display_rms: float = float("nan")
    final_relative_rms_linear: float = float("nan")
    error_at_peer_seconds: float | None = None  # display RMS of the last pass done by smallppm's time
    extrapolated_seconds_to_reach: float | None = None  # power-law fit, when not reached
    # per pass: (render seconds, photon paths, display RMS, relative linear RMS)
    curve: list[tuple[float, int, float, float]] = field(default_factory=list)


def load_reference() -> np.ndarray:
    """The reference as (H, W, 3) float64 linear radiance."""
    return read_image(REFERENCE_FILE)[..., :3].astype(np.float64)


def to_reference_size(img: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """Our image at the reference's size (2x2 box filter when the reference is half size)."""
    if img.shape[:2] == ref.shape[:2]:
        return img
    if img.shape[0] == 2 * ref.shape[0] and img.shape[1] == 2 * ref.shape[1]:
        return box2x2(img)
    raise ValueError(f"image {img.shape[:2]} does not match reference {ref.shape[:2]}")


def render_until(photons_per_pass: int | None, ref: np.ndarray, target: float, peer_seconds: float, gather: str,
                 seed: int = 0) -> Run:
    """Render passes until the display RMS is <= target or the clock passes the cap."""
    ref_display = display(ref)
    ref_norm = float(np.sqrt(np.mean(ref ** 2)))
    t0 = time.perf_counter()
    eng = bench_engine("smallppm", gather=gather, photons_per_pass=photons_per_pass, seed=seed)
    state = eng.start()
    setup = time.perf_counter() - t0
    run = Run(photons_per_pass=eng.settings.paths_per_pass, gather=gather, setup_seconds=setup)
    h, w = eng.arrays.height, eng.arrays.width

    def observe(st: object, seconds: float) -> bool:
        clock = setup + seconds
        img = to_reference_size(eng.integrator.image(st).reshape(h, w, 3), ref)
        err = display_rms(img, ref_display)
        rel = float(np.sqrt(np.mean((img - ref) ** 2))) / ref_norm
        run.curve.append((clock, st.emitted, err, rel))
        if err <= target:
            run.reached, run.seconds_to_reach, run.paths_to_reach = True, clock, st.emitted
            run.ratio = peer_seconds / clock
        return run.reached

    render(eng, seconds=CAP_FACTOR * peer_seconds - setup, progress=observe, state=state)
    summarize(run, target, peer_seconds)
    return run


def summarize(run: Run, target: float, peer_seconds: float) -> None:
    """Fill the final errors, the error at smallppm's time and, if the target was not
    reached, the time to reach it extrapolated from a power law over the last half."""
    c = np.array(run.curve)
    run.final_display_rms, run.final_relative_rms_linear = float(c[-1, 2]), float(c[-1, 3])
    done = c[c[:, 0] <= peer_seconds]
    run.error_at_peer_seconds = float(done[-1, 2]) if len(done) else None
    if not run.reached and len(c) >= 8:
        slope, intercept = np.polyfit(np.log(c[len(c) // 2:, 0]), np.log(c[len(c) // 2:, 2]), 1)
        if slope < 0:
            run.extrapolated_seconds_to_reach = float(np.exp((np.log(target) - intercept) / slope))


def chart(runs: list[Run], peer: dict) -> None:
    """Error vs render time for our runs, smallppm's (time, error) marked."""
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.5, 5))
    for run in runs:
        t = [c[0] for c in run.curve]
        e = [c[2] for c in run.curve]
        label = f"photonfarm {run.gather}, 2^{run.photons_per_pass.bit_length() - 1} paths/pass"
        if run.reached:
            label += f": {run.seconds_to_reach:.1f} s, ratio {run.ratio:.2f}"
        elif run.extrapolated_seconds_to_reach:
            label += f": not reached, ~{run.extrapolated_seconds_to_reach:.0f} s extrapolated"
        ax.loglog(t, e, label=label)
    ax.plot([peer["seconds"]], [peer["display_rms_vs_reference"]], "r*", markersize=14,
            label=f"smallppm, {peer['photon_paths'] / 1e6:.0f}M paths: {peer['seconds']:.1f} s")
    ax.axhline(peer["display_rms_vs_reference"], color="r", lw=0.6, ls=":")
    ax.axvline(peer["seconds"] / GOAL_RATIO, color="g", lw=0.8, ls="--", label="goal: 1/5 of smallppm's time")
    ax.set_xlabel("render time, s (set-up included)")
    ax.set_ylabel("display-space RMS vs reference")
    ax.set_title("smallppm scene, 1024x768: error vs time")
    ax.legend(fontsize=8)
    ax.grid(True, which="both", lw=0.3)
    fig.tight_layout()
    save_figure(fig, "peer_smallppm")


def main() -> None:
    parser = argparse.ArgumentParser(description="Time to reach smallppm's image error, and the speed ratio.")
    parser.add_argument("--photons-per-pass", type=int, default=None, help="default: the engine's for the frame")
    parser.add_argument("--gather", choices=("exact", "stochastic"), default=DEFAULTS.gather)
    parser.add_argument("--sweep", action="store_true",
                        help=f"both gathers, each with every photons_per_pass in {CANDIDATES}")
    parser.add_argument("--peer-image", help="instead: print a smallppm image.ppm's display RMS vs the reference")
    args = parser.parse_args()
    ref = load_reference()
    if args.peer_image:
        peer_img = read_ppm(args.peer_image)
        if peer_img.shape[:2] != ref.shape[:2]:
            peer_img = box2x2(peer_img)  # display values box-filtered: an approximation at half size
        for name, img in (("as read", peer_img), ("flipped vertically", peer_img[::-1])):
            print(f"{name}: display RMS {float(np.sqrt(np.mean((img - display(ref)) ** 2))):.5f}")
        return
    peer = json.loads(PEERS_FILE.read_text())["smallppm"]
    target, peer_seconds = peer["display_rms_vs_reference"], peer["seconds"]
    runs = []
    configs = [(g, p) for g in ("exact", "stochastic") for p in CANDIDATES] if args.sweep \
        else [(args.gather, args.photons_per_pass)]
    for gather, ppp in configs:
        run = render_until(ppp, ref, target, peer_seconds, gather)
        status = (f"reached {target:.4f} in {run.seconds_to_reach:.1f} s ({run.paths_to_reach / 1e6:.1f}M paths), "
                  f"ratio {run.ratio:.2f}" if run.reached else
                  f"not reached in {run.curve[-1][0]:.1f} s: error {run.final_display_rms:.4f} > {target:.4f}, "
                  f"{run.error_at_peer_seconds:.4f} at {peer_seconds:.1f} s; "
                  f"extrapolated {run.extrapolated_seconds_to_reach or float('nan'):.0f} s")
        print(f"{gather} gather, photons_per_pass {ppp}: {status}", flush=True)
        runs.append(run)
    report = {
        "measured": time.strftime("%Y-%m-%d %H:%M:%S"),
        "smallppm": peer,
        "target_display_rms": target,
        "cap_seconds": CAP_FACTOR * peer_seconds,
        "goal_ratio": GOAL_RATIO,
        "reference": str(REFERENCE_FILE.relative_to(REFERENCE_FILE.parents[2])),
        "reference_resolution": [ref.shape[1], ref.shape[0]],
        "settings": {"method": "sppm", "alpha": DEFAULTS.alpha, "seed": 0},
        "runs": [asdict(r) for r in runs],
    }
    path = write_json("peer_smallppm", report)
    chart(runs, peer)
    print(f"wrote {path} and peer_smallppm.png")


if __name__ == "__main__":
    main()
