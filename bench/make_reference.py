"""Render a cached reference image: bench/reference/<name>.exr with a JSON sidecar.

Two independent SPPM runs (exact gather, alpha 0.7, seeds 101 and 102 unless given), each
for --seconds, averaged; half the RMS difference of the two runs estimates the average's
own error (their noise is independent: rms(A - B) ~ sqrt(2) e_run, e_avg ~ e_run / sqrt(2)).

    python -m bench.make_reference smallppm --seconds 270 --photons-per-pass 1048576 --out smallppm-ref
    python -m bench.make_reference cornell-caustics --resolution 48x48 --seconds 120 --photon-only

--photon-only keeps the photon-density part S/E alone (no directly seen emission), which is
what the error estimator bounds (tests/test_error_estimation.py).

--mitsuba-spp N renders with Mitsuba 3's path tracer instead (independent of photonfarm,
bench/mitsuba_peer.py), N samples per pixel for each of the two seeds:

    python -m bench.make_reference cornell-box --resolution 96x96 --mitsuba-spp 4096 --out cornell-box-corners-96x96

With --photon-only, Mitsuba renders each chunk twice with the same seed: the scene, and the
scene with every diffuse albedo 0, which leaves exactly the emission seen directly or through
specular and glossy surfaces (our eye pass's Ld: it stops at the first diffuse surface). The
difference is the photon-density part; the two share their camera rays, so pixels that see a
light's edge subtract their coverage noise away:

    python -m bench.make_reference cornell-caustics --resolution 48x48 --mitsuba-spp 65536 --photon-only
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from bench.common import BENCH_DIR, bench_engine
from bench.mitsuba_peer import render as mitsuba_render
from kernels.contract import LUMINANCE
from service.cli import _resolution
from worker.image_io import write_image
from worker.render_loop import render as render_passes
from worker.scene import Diffuse, Scene, bundled_scene_path, load_scene_file


def render(scene: str, resolution: tuple[int, int] | None, photons: int, seed: int, seconds: float,
           photon_only: bool) -> tuple[np.ndarray, int]:
    eng = bench_engine(scene, resolution, gather="exact", photons_per_pass=photons, seed=seed, alpha=0.7)
    st = render_passes(eng, seconds=seconds)
    rgb = st.photon_radiance() if photon_only else st.radiance()
    return rgb.reshape(eng.arrays.height, eng.arrays.width, 3), st.passes


def seen_emission_scene(scene: Scene) -> Scene:
    """The scene with no diffuse reflection: what remains is the emission a camera sees
    directly or through specular and glossy surfaces."""
    black = {name: m.model_copy(update={"albedo": (0.0, 0.0, 0.0)}) if isinstance(m, Diffuse) else m
             for name, m in scene.materials.items()}
    return scene.model_copy(update={"materials": black})


def render_mitsuba(scene: str, resolution: tuple[int, int] | None, spp: int, seed: int,
                   photon_only: bool = False) -> tuple[np.ndarray, float]:
    """Mitsuba path tracing in chunks of 256 spp (each its own seed): (image, seconds); with
    `photon_only`, less the emission seen directly (`seen_emission_scene`, same seeds)."""
    parsed, base = load_scene_file(bundled_scene_path(scene))
    res = resolution or parsed.camera.resolution
    total, seconds = np.zeros((res[1], res[0], 3)), 0.0
    chunks = max(1, spp // 256)
    seen = seen_emission_scene(parsed) if photon_only else None
    for k in range(chunks):
        chunk_seed = seed * 1_000_000 + k
        img, t = mitsuba_render(parsed, base, res, spp // chunks, "path", seed=chunk_seed)
        total, seconds = total + img, seconds + t
        if seen is not None:
            img, t = mitsuba_render(seen, base, res, spp // chunks, "path", seed=chunk_seed)
            total, seconds = total - img, seconds + t
    return total / chunks, seconds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scene")
    parser.add_argument("--resolution", type=_resolution)
    parser.add_argument("--seconds", type=float, default=120.0, help="render time of each of the two runs")
    parser.add_argument("--photons-per-pass", type=int, default=1 << 18)
    parser.add_argument("--photon-only", action="store_true")
    parser.add_argument("--seeds", type=int, nargs=2, default=(101, 102))
    parser.add_argument("--mitsuba-spp", type=int, help="Mitsuba path tracing, this many spp per seed")
    parser.add_argument("--out", help="file name without suffix (default: SCENE-WxH)")
    args = parser.parse_args()
    if args.mitsuba_spp:
        runs = [render_mitsuba(args.scene, args.resolution, args.mitsuba_spp, seed, args.photon_only)
                for seed in args.seeds]
    else:
        runs = [render(args.scene, args.resolution, args.photons_per_pass, seed, args.seconds, args.photon_only)
                for seed in args.seeds]
    (a, passes_a), (b, passes_b) = runs
    ref = 0.5 * (a + b)
    name = args.out or f"{args.scene}-{ref.shape[1]}x{ref.shape[0]}"
    path = BENCH_DIR / "reference" / f"{name}.exr"
    path.parent.mkdir(parents=True, exist_ok=True)
    write_image(path, ref)
    own_error = float(np.sqrt(np.mean(((a - b) @ LUMINANCE) ** 2)) / 2.0)
    if args.mitsuba_spp:
        info = {"scene": args.scene, "resolution": [ref.shape[1], ref.shape[0]],
                "method": "mitsuba path tracer (scalar_rgb, max_depth -1, box filter), independent of photonfarm",
                "spp_per_run": args.mitsuba_spp, "seeds": list(args.seeds), "seconds_per_run": [passes_a, passes_b],
                "quantity": "photon-density radiance S/E only (less the emission seen directly: the same seeds with "
                            "every diffuse albedo 0)" if args.photon_only else "radiance",
                "estimated_luminance_rms_error": own_error}
    else:
        info = {"scene": args.scene, "resolution": [ref.shape[1], ref.shape[0]], "method": "sppm", "gather": "exact",
                "alpha": 0.7, "photons_per_pass": args.photons_per_pass, "passes": [passes_a, passes_b],
                "seeds": list(args.seeds), "seconds_per_run": args.seconds,
                "quantity": "photon-density radiance S/E only" if args.photon_only else "radiance",
                "estimated_luminance_rms_error": own_error}
    path.with_suffix(".json").write_text(json.dumps(info, indent=1) + "\n")
    print(json.dumps(info))


if __name__ == "__main__":
    main()
