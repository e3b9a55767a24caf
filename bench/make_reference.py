"""Render the converged reference of smallppm's scene: bench/reference/smallppm-ref.exr.

SPPM, exact gather, 2^20 photon paths per pass, alpha 0.7, from smallppm's camera
(bench.common.smallppm_scene). Two independent runs (seeds 1 and 2), each for
--seconds of rendering, are averaged; half the display-space RMS between the two runs
estimates the reference's own error (each run's noise is independent, so
rms(A - B) ~ sqrt(2) e_run and the average has e ~ e_run / sqrt(2)). The result is a
float32 EXR at full resolution, or box-filtered to half resolution with --half.

    python -m bench.make_reference --seconds 270
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from bench.common import REFERENCE_FILE, box2x2, display, smallppm_scene
from worker.engine import Engine, RenderSettings
from worker.image_io import write_image
from worker.stats import Accumulators

PHOTONS_PER_PASS = 1 << 20


def render(seed: int, seconds: float) -> tuple[np.ndarray, int]:
    """One SPPM run for `seconds`; returns the (H, W, 3) linear image and its passes."""
    scene, base = smallppm_scene()
    eng = Engine(scene, base, RenderSettings(method="sppm", gather="exact", photons_per_pass=PHOTONS_PER_PASS,
                                             seed=seed))
    acc = Accumulators.start(0.7, eng.initial_radius())
    start = time.perf_counter()
    while time.perf_counter() - start < seconds:
        acc.merge(eng.run_batch(acc.radius(), acc.passes, 1))
        print(f"seed {seed}: {acc.passes} passes, {time.perf_counter() - start:.0f} s", flush=True)
    return acc.radiance().reshape(eng.arrays.height, eng.arrays.width, 3), acc.passes


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=270.0, help="render time per run (two runs)")
    parser.add_argument("--half", action="store_true", help="save at half resolution (2x2 box filter)")
    args = parser.parse_args()
    (a, passes_a), (b, passes_b) = render(1, args.seconds), render(2, args.seconds)
    ref = 0.5 * (a + b)
    est_error = float(np.sqrt(np.mean((display(a) - display(b)) ** 2))) / 2.0
    if args.half:
        ref = box2x2(ref)
    REFERENCE_FILE.parent.mkdir(parents=True, exist_ok=True)
    write_image(REFERENCE_FILE, ref)
    info = {"passes": [passes_a, passes_b], "photons_per_pass": PHOTONS_PER_PASS,
            "photon_paths": (passes_a + passes_b) * PHOTONS_PER_PASS, "resolution": [ref.shape[1], ref.shape[0]],
            "estimated_display_rms_error": est_error}
    print(json.dumps(info))
    REFERENCE_FILE.with_suffix(".json").write_text(json.dumps(info, indent=1) + "\n")


if __name__ == "__main__":
    main()
