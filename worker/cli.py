"""`photonfarm render`: render a scene locally, with a progress bar."""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

from worker.engine import MAX_PHOTONS_PER_PASS, Engine, RenderSettings
from worker.image_io import write_image
from worker.scene import MAX_PIXELS, MAX_RESOLUTION, SceneError, bundled_scene_path, load_scene_file
from worker.stats import Accumulators


def _resolution(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT, got {text!r}") from None
    if not (1 <= w <= MAX_RESOLUTION and 1 <= h <= MAX_RESOLUTION):
        raise argparse.ArgumentTypeError(f"each side must lie in 1..{MAX_RESOLUTION}")
    if w * h > MAX_PIXELS:
        raise argparse.ArgumentTypeError(f"at most {MAX_PIXELS} pixels")
    return w, h


def _positive(kind: type) -> object:
    def parse(text: str) -> object:
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
        if not value > 0 or value != value or value == float("inf"):
            raise argparse.ArgumentTypeError(f"must be positive and finite, got {text}")
        return value
    return parse


def _alpha(text: str) -> float:
    value = _positive(float)(text)
    if value > 1.0:
        raise argparse.ArgumentTypeError("alpha must lie in (0, 1]")
    return value  # type: ignore[return-value]


def _output(text: str) -> Path:
    path = Path(text)
    if path.suffix.lower() not in (".exr", ".png"):
        raise argparse.ArgumentTypeError("output must end in .exr or .png")
    return path


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="photonfarm", description="Progressive photon mapping render service.")
    sub = parser.add_subparsers(dest="command", required=True)
    render = sub.add_parser("render", help="render a scene on this machine")
    render.add_argument("scene", help="bundled scene name (see scenes/) or path to a scene .json")
    budget = render.add_mutually_exclusive_group(required=True)
    budget.add_argument("--passes", type=_positive(int), help="number of photon passes")
    budget.add_argument("--seconds", type=_positive(float), help="render for this long")
    render.add_argument("--photons-per-pass", type=_positive(int), default=RenderSettings.photons_per_pass)
    render.add_argument("--alpha", type=_alpha, default=0.7, help="fraction of photons kept per pass (default 0.7)")
    render.add_argument("--method", choices=("sppm", "ppm"), default="sppm")
    render.add_argument("--gather", choices=("stochastic", "exact"), default="stochastic")
    render.add_argument("--resolution", type=_resolution, help="override the scene's WIDTHxHEIGHT")
    render.add_argument("--seed", type=int, default=0)
    render.add_argument("--radius", type=_positive(float), help="initial radius in world units "
                        "(default: 2 pixel footprints at each pixel's first diffuse hit)")
    render.add_argument("--out", type=_output, required=True, help="output image, .exr (linear) or .png")

    serve = sub.add_parser("serve", help="run the HTTP API (with embedded Redis and local workers by default)")
    serve.add_argument("--host", default="127.0.0.1")
    serve.add_argument("--port", type=int, default=8000)
    serve.add_argument("--workers", type=int, default=None, help="local worker processes (default: one per core)")
    serve.add_argument("--redis-url", default=os.environ.get("REDIS_URL"),
                       help="external Redis (default: $REDIS_URL, else an embedded one)")
    serve.add_argument("--data-dir", type=Path, default=Path(os.environ.get("PHOTONFARM_DATA", "data")),
                       help="where the embedded Redis keeps its append-only file (default: ./data)")

    from service.client import add_parser as add_submit_parser  # the HTTP client lives with the API

    add_submit_parser(sub, _positive(float), _positive(int), _resolution)

    worker = sub.add_parser("worker", help="run a render worker for the Redis at --redis-url")
    worker.add_argument("--redis-url", default=os.environ.get("REDIS_URL"), required="REDIS_URL" not in os.environ)
    worker.add_argument("--burst", action="store_true", help="exit when the queues are empty")
    return parser


def _progress(passes: int, total: int | None, photons: int, elapsed: float, seconds: float | None) -> None:
    frac = passes / total if total else min(elapsed / seconds, 1.0) if seconds else 0.0
    bar = "#" * int(30 * frac)
    rate = photons / elapsed if elapsed > 0 else 0.0
    sys.stderr.write(f"\r[{bar:<30}] {passes} passes  {rate / 1e6:6.2f} M photons/s  {elapsed:7.1f} s")
    sys.stderr.flush()


def render(args: argparse.Namespace) -> int:
    path = Path(args.scene) if args.scene.endswith(".json") else bundled_scene_path(args.scene)
    scene, base_dir = load_scene_file(path)
    if args.photons_per_pass > MAX_PHOTONS_PER_PASS:
        raise SceneError("photons_per_pass", f"at most {MAX_PHOTONS_PER_PASS}")
    settings = RenderSettings(method=args.method, gather=args.gather, photons_per_pass=args.photons_per_pass,
                              seed=args.seed, initial_radius=args.radius)
    engine = Engine(scene, base_dir, settings, resolution=args.resolution)
    state = Accumulators.start(args.alpha, engine.initial_radius())
    start = time.perf_counter()
    k = 0
    while (args.passes and k < args.passes) or (args.seconds and time.perf_counter() - start < args.seconds):
        state.merge(engine.run_batch(state.radius(), k, 1))
        k += 1
        _progress(k, args.passes, state.emitted, time.perf_counter() - start, args.seconds)
    sys.stderr.write("\n")
    a = engine.arrays
    write_image(args.out, state.radiance().reshape(a.height, a.width, 3))
    print(f"wrote {args.out}: {state.passes} passes, {state.emitted} photons, {time.perf_counter() - start:.1f} s")
    return 0


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.command == "serve":
        from service.serve import serve  # the HTTP stack is only needed here

        return serve(args.host, args.port, args.workers, args.redis_url, args.data_dir,
                     os.environ.get("PHOTONFARM_TOKEN") or None)
    if args.command == "worker":
        from worker.queue_worker import run_worker

        return run_worker(args.redis_url, burst=args.burst)
    if args.command == "submit":
        from service.client import ClientError, submit

        try:
            return submit(args)
        except ClientError as exc:
            print(f"photonfarm: {exc}", file=sys.stderr)
            return 2
    try:
        return render(args)
    except SceneError as exc:
        print(f"photonfarm: bad scene: {exc}", file=sys.stderr)
        return 2
    except ValueError as exc:
        print(f"photonfarm: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
