"""`photonfarm`: render locally, run the service or a worker, submit to a service, and
check or convert scenes. Render flags take their defaults and help from the settings
model (worker/settings.py) and are validated by it."""

from __future__ import annotations

import argparse
import ipaddress
import json
import sys
import time
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

from pydantic import ValidationError

from worker.allocator import retain_large_allocations
from worker.config import URL_SCHEMES, ConfigError, config
from worker.outputs import check_writable, make_folder
from worker.scene import MAX_PIXELS, MAX_RESOLUTION, SceneError, bundled_scene_path, load_any_scene, scene_file
from worker.settings import Settings

# Render flags that are settings fields, by flag name (defaults and help from the model).
RENDER_FIELDS = ("method", "gather", "direct", "sampler", "target_acceptance", "alpha", "photons_per_pass",
                 "initial_radius", "seed", "resolution")


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


def _positive(kind: type) -> Any:
    def parse(text: str) -> object:
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
        if not value > 0 or value != value or value == float("inf"):
            raise argparse.ArgumentTypeError(f"must be positive and finite, got {text}")
        return value
    return parse


def _count(text: str) -> int:
    """A number of things, 0 included."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a whole number: {text!r}") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be 0 or more, got {text}")
    return value


def _redis_url(text: str) -> str:
    """A Redis URL without a password (the value is not echoed back): a command line is
    readable by any local user, so a password goes in REDIS_URL or REDIS_URL_FILE."""
    parts = urlsplit(text)
    if parts.scheme not in URL_SCHEMES:
        raise argparse.ArgumentTypeError("expected a redis://, rediss:// or unix:// URL")
    if parts.password or "password=" in parts.query:
        raise argparse.ArgumentTypeError("a password on the command line is readable by any local user: "
                                         "give the URL in REDIS_URL or REDIS_URL_FILE")
    return text


def loopback(host: str) -> bool:
    """Whether binding `host` reaches this machine alone: localhost, 127.0.0.0/8 or ::1."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False  # another name: it may resolve to any interface


def _output(text: str) -> Path:
    path = Path(text)
    if path.suffix.lower() not in (".exr", ".png"):
        raise argparse.ArgumentTypeError("output must end in .exr or .png")
    return path


def _add_setting(parser: argparse.ArgumentParser, name: str) -> None:
    """A flag for a settings field, with the model's default, choices and help."""
    info = Settings.model_fields[name]
    flag = "--" + {"initial_radius": "radius"}.get(name, name).replace("_", "-")
    kwargs: dict[str, Any] = {"dest": name, "default": info.default}
    choices = getattr(info.annotation, "__args__", None)
    if name == "resolution":
        kwargs["type"] = _resolution
    elif choices and all(isinstance(c, str) for c in choices):
        kwargs["choices"] = choices
    else:
        kwargs["type"] = {"alpha": float, "initial_radius": float, "target_acceptance": float}.get(name, int)
    default = f" (default: {info.default})" if info.default is not None else ""
    parser.add_argument(flag, help=f"{info.description}{default}", **kwargs)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="photonfarm", description="Progressive photon mapping render service.")
    sub = parser.add_subparsers(dest="command", required=True)
    render = sub.add_parser("render", help="render a scene on this machine")
    render.add_argument("scene", help="bundled scene name (see scenes/), or a scene .json or Mitsuba 3 .xml file "
                                      "(its meshes beside it)")
    budget = render.add_mutually_exclusive_group(required=True)
    budget.add_argument("--passes", type=_positive(int), help="number of photon passes")
    budget.add_argument("--seconds", type=_positive(float), help="render for this long")
    for name in RENDER_FIELDS:
        _add_setting(render, name)
    render.add_argument("--out", type=_output, required=True, help="output image, .exr (linear) or .png")

    convert = sub.add_parser("convert", help="write our scene JSON from a Mitsuba 3 XML scene")
    convert.add_argument("scene", type=Path, help="a Mitsuba 3 .xml scene")
    convert.add_argument("--param", action="append", default=[], metavar="NAME=VALUE",
                         help="a $NAME substitution (overrides the file's <default>); repeatable")
    convert.add_argument("--out", type=Path, help="JSON file to write (default: standard output)")

    serve = sub.add_parser("serve", help="run the HTTP API (with embedded Redis and local workers by default)")
    serve.add_argument("--host", default="127.0.0.1",
                       help="the address to bind (default: 127.0.0.1); beyond loopback only with a token")
    serve.add_argument("--port", type=int, default=8000)
    serve.add_argument("--workers", type=_count, default=None,
                       help="local worker processes (default: one per core; 0: workers run elsewhere)")
    serve.add_argument("--reducers", type=_count, default=1,
                       help="local reducer processes, which fold jobs and publish their images (default: 1; "
                            "0: reducers run elsewhere)")
    serve.add_argument("--redis-url", type=_redis_url,
                       help="external Redis (default: $REDIS_URL or the file $REDIS_URL_FILE names, else an "
                            "embedded one)")
    serve.add_argument("--data-dir", type=Path,
                       help="where the embedded Redis keeps its append-only file (default: $PHOTONFARM_DATA, "
                            "else ./data)")

    from service.client import add_parser as add_submit_parser

    add_submit_parser(sub, _positive(float), _positive(int), _resolution, _output)

    reducer = sub.add_parser("reducer", help="run a reducer (folds jobs, publishes their images, re-issues lost "
                                             "batches) for the Redis at --redis-url")
    reducer.add_argument("--redis-url", type=_redis_url,
                         help="the Redis (default: $REDIS_URL or the file $REDIS_URL_FILE names)")

    worker = sub.add_parser("worker", help="run a render worker for the Redis at --redis-url")
    worker.add_argument("--redis-url", type=_redis_url,
                        help="the Redis (default: $REDIS_URL or the file $REDIS_URL_FILE names)")
    worker.add_argument("--burst", action="store_true",
                        help="exit when the queues are empty (status 1 if Redis stays out of reach)")
    return parser


def render(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from worker.engine import Engine
    from worker.outputs import write_render
    from worker.render_loop import render as render_passes
    from worker.store.published import Published

    notes: list[str] = []
    scene, base_dir = load_any_scene(_scene_path(args.scene), notes=notes)
    for line in notes:
        print(f"photonfarm: {line}", file=sys.stderr)
    try:
        settings = Settings(**{name: getattr(args, name) for name in RENDER_FIELDS},
                            max_passes=args.passes, max_seconds=args.seconds)
    except ValidationError as exc:
        err = exc.errors()[0]
        raise ValueError(f"--{'-'.join(str(p) for p in err['loc']).replace('_', '-')}: {err['msg']}") from None
    check_writable(args.out)
    try:
        engine = Engine(scene, base_dir, settings)
        state = engine.start()
    except KeyboardInterrupt:
        print("interrupted before the first pass: nothing written", file=sys.stderr)
        return 130
    start = time.perf_counter()
    total = args.passes or args.seconds
    with tqdm(total=total, unit="pass" if args.passes else "s", disable=None, file=sys.stderr,
              bar_format="{l_bar}{bar}| {n:.0f}/{total:.0f} [{elapsed}<{remaining}] {postfix}") as bar:
        def progress(st: Any, elapsed: float) -> None:
            bar.n = st.passes if args.passes else min(elapsed, args.seconds)
            bar.set_postfix_str(f"{st.emitted / max(elapsed, 1e-9) / 1e6:.2f} M photons/s", refresh=True)

        interrupted = False
        try:
            render_passes(engine, passes=args.passes, seconds=args.seconds, progress=progress, state=state)
        except KeyboardInterrupt:
            interrupted = True
    write_render(args.out, engine.integrator.settings, Published.of(engine.integrator, state), engine.arrays.width,
                 engine.arrays.height)
    for line in engine.integrator.notes(state.counters):  # what the method decided (sampler auto's choice)
        print(f"photonfarm: {line}", file=sys.stderr)
    note = " (interrupted: the image so far)" if interrupted else ""
    print(f"wrote {args.out}{note}: {state.passes} passes, {state.emitted} photons, "
          f"{time.perf_counter() - start:.1f} s")
    return 130 if interrupted else 0


def _scene_path(scene: str) -> Path:
    """A scene file by path (.json or .xml), or a bundled scene by name."""
    return scene_file(scene) or bundled_scene_path(scene)


def convert(args: argparse.Namespace) -> int:
    from worker.mitsuba_scene import convert_mitsuba

    params = {}
    for item in args.param:
        name, sep, value = item.partition("=")
        if not sep or not name:
            raise ValueError(f"--param wants NAME=VALUE, got {item!r}")
        params[name] = value
    notes: list[str] = []
    text = json.dumps(convert_mitsuba(args.scene, params, notes=notes), indent=1)
    for line in notes:
        print(f"photonfarm: {line}", file=sys.stderr)
    if args.out is None:
        print(text)
    else:
        make_folder(args.out)
        args.out.write_text(text + "\n")
        print(f"wrote {args.out}")
    return 0


def main(argv: list[str] | None = None) -> int:
    retain_large_allocations()
    try:
        settings = config()
    except ConfigError as exc:
        print(f"photonfarm: {exc}", file=sys.stderr)
        return 2
    parser = build_parser()
    args = parser.parse_args(argv)
    redis_url = getattr(args, "redis_url", None) or settings.redis_url
    if args.command == "serve":
        from service.serve import serve  # the HTTP stack is only needed here

        if settings.token is None and not loopback(args.host):
            print(f"photonfarm: serve --host {args.host} is reachable beyond this machine: set PHOTONFARM_TOKEN "
                  "or PHOTONFARM_TOKEN_FILE first (docs/farm.md, Security model)", file=sys.stderr)
            return 2

        return serve(args.host, args.port, args.workers, args.reducers, redis_url, args.data_dir or settings.data,
                     settings.token)
    if args.command == "reducer":
        from worker.reducer import run as run_reducer

        if redis_url is None:
            parser.error("reducer: no Redis: set REDIS_URL (or REDIS_URL_FILE) or give --redis-url")
        return run_reducer(redis_url)
    if args.command == "worker":
        from worker.queue_worker import run_worker

        if redis_url is None:
            parser.error("worker: no Redis: set REDIS_URL (or REDIS_URL_FILE) or give --redis-url")
        return run_worker(redis_url, burst=args.burst)
    if args.command == "submit":
        from service.client import ClientError, submit

        try:
            return submit(args)
        except ClientError as exc:
            print(f"photonfarm: {exc}", file=sys.stderr)
            return 2
    try:
        return convert(args) if args.command == "convert" else render(args)
    except SceneError as exc:
        print(f"photonfarm: bad scene: {exc}", file=sys.stderr)
        return 2
    except ValueError as exc:
        print(f"photonfarm: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
