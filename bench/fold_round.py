"""A fold round's cost by stage: CPU seconds of the folder and of Redis.

One SPPM job (the service's defaults: exact gather, error estimation) of the given frame
size on one embedded redis-server (service/redis_server.py: append-only file, fsync on
every write). Per round, `--batches` synthetic batches are pushed and accepted as workers
do (Jobs.merge), then one fold round runs in this process as the API's folder runs it
(Jobs.fold): in memory, or every `--checkpoint-every`-th round (or when the checkpoint rule
says so) a checkpoint that writes the state to the tiles. A batch's sums look like a
render's: a band of background (no measurement point, every sum zero), a band of never-lit
pixels (only H), a small emitter seen directly (Ld), and lit pixels with every sum; values
differ per batch (seeded).

Reported per round, and the mean of the rounds after the first of each kind (memory,
checkpoint; the first round's state read is from Redis, the later ones from the folder's
tile cache, as in the API; Redis's CPU moves with when its append-only-file rewrites land,
so take the mean of several rounds): the folder's CPU seconds per stage of
`TiledState.fold_round` (read state, read and merge deltas, inputs, estimate, write), the
rest of `Jobs.fold` (lease, record, accounting), Redis's CPU seconds over the round
(its append-only-file rewrites included), a batch's merge before the round (the pushing
process's CPU seconds, as a worker's: encoding, sending, accepting; and Redis's), and, on
the folded state, what an image read
costs (`Jobs.state` from the cache and `Integrator.image`) and the error estimate's
parts (radius, bias estimate, discontinuity bias, never-lit bound, the whole estimate).
CPU seconds, not wall time: the machine is shared and load moves CPU time little.

    python -m bench.fold_round                       # 1920x1080 and 3840x2160
    python -m bench.fold_round --sizes 640x360 --rounds 2   # a quick check that it runs
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from bench.common import cpu_seconds, write_json
from service.redis_server import EmbeddedRedis
from worker.allocator import retain_large_allocations
from worker.error_estimate import bias_estimate, blocks, discontinuity_bias, edge_quantiles, unlit_bound, unlit_scale
from worker.integrators.base import Delta
from worker.settings import Settings
from worker.stats import radius
from worker.store import Batch, Jobs, keys
from worker.store.connection import connect

PASSES_PER_BATCH = 4
EMITTED_PER_PASS = 1 << 18


def synthetic_delta(layout_names: dict[str, int], w: int, h: int, passes: int, rng: np.random.Generator) -> dict:
    """A batch's sums shaped like a render's (module docstring)."""
    n = w * h
    rows = np.repeat(np.arange(h), w)
    background, unlit = rows < h // 8, (rows >= h // 8) & (rows < h // 4)
    lit = ~(background | unlit)
    emitter = lit & (rows < h // 4 + h // 20) & (np.tile(np.arange(w), h) < w // 10)
    lum = rng.uniform(0.2, 1.0, n)
    sums: dict[str, np.ndarray] = {}
    for name, width in layout_names.items():
        shape = (n, width) if width > 1 else (n,)
        sums[name] = np.zeros(shape)
    sums["H"][~background] = passes
    d = rng.uniform(50.0, 150.0, n) * passes
    sums["D"][lit] = d[lit]
    sums["M"][lit] = rng.uniform(10.0, 30.0, n)[lit] * passes  # photons counted
    sums["S"][lit] = (lum * EMITTED_PER_PASS * passes)[lit, None] * rng.uniform(0.8, 1.2, (int(lit.sum()), 3))
    sums["Ld"][emitter] = passes * 5.0
    sums["G"][lit] = (rng.normal(0.0, 1.0, n) * EMITTED_PER_PASS * passes)[lit]
    x = lum * rng.uniform(0.9, 1.1, n)
    sums["X1"][lit] = (x * passes)[lit]
    sums["X2"][lit] = (x * x * passes * 1.05)[lit]
    sums["L2"][lit] = (rng.uniform(0.5, 2.0, n) * passes)[lit]
    dh = rng.normal(0.0, 0.05, n) * lum
    sums["Dh"][lit] = (dh * passes)[lit]
    sums["Dh2"][lit] = (dh * dh * passes + 0.01 * lum * lum * passes)[lit]
    return sums


def _cpu(f, *args):
    t0 = time.process_time()
    out = f(*args)
    return out, time.process_time() - t0


def run(w: int, h: int, rounds: int, batches: int, checkpoint_every: int, data_dir: Path) -> dict:
    server = EmbeddedRedis(data_dir, maxmemory="0").start(supervise=False)
    try:
        store = Jobs(connect(server.url))
        job_id = store.create({}, Settings(max_passes=10 ** 7), w, h, None)
        record = store.get(job_id)
        store.init_setup(record, {"R0": np.full(w * h, 0.01)})
        store.r.hset(keys.job(job_id), mapping={"status": "running", "started": time.time()})
        widths = dict(record.integrator.sums.widths)
        rng = np.random.default_rng(14)
        per_round = []
        for r in range(rounds):
            push_cpu = push_redis_cpu = 0.0  # the batches' merges (a worker's push and accept)
            for b in range(batches):
                first = (r * batches + b) * PASSES_PER_BATCH
                sums = synthetic_delta(widths, w, h, PASSES_PER_BATCH, rng)
                delta = Delta(first, PASSES_PER_BATCH, EMITTED_PER_PASS * PASSES_PER_BATCH, sums)
                redis_before, cpu_before = cpu_seconds([server.proc.pid]), time.process_time()
                assert store.merge(Batch(job_id, first, PASSES_PER_BATCH), delta, 1.0) == "merged"
                push_cpu += time.process_time() - cpu_before
                push_redis_cpu += cpu_seconds([server.proc.pid]) - redis_before
            del sums, delta
            redis_before = cpu_seconds([server.proc.pid])
            cpu_before, wall_before = time.process_time(), time.perf_counter()
            folded = store.fold(job_id, checkpoint=(r + 1) % checkpoint_every == 0)
            fold_cpu, redis_cpu = time.process_time() - cpu_before, cpu_seconds([server.proc.pid]) - redis_before
            fold_wall = time.perf_counter() - wall_before
            assert folded is not None, "the round folded nothing"
            stages = dict(folded.stages)
            stages["other (lease, record, accounting)"] = fold_cpu - sum(stages.values())
            record = store.get(job_id)
            # What an image read costs, and the error estimate's parts, on the folded state.
            state, read_cpu = _cpu(store.state, record)
            _, image_cpu = _cpu(record.integrator.image, state)
            settings = record.integrator.settings
            r_now, radius_cpu = _cpu(radius, state.R0, state.N, state.D)
            state._radius = None
            state.radius()
            b_est, bias_cpu = _cpu(bias_estimate, r_now, state.G, state.emitted, settings.bias_constant)
            bias_se = np.abs(b_est) * 0.1  # any standard error: the cost does not depend on it
            _, edge_cpu = _cpu(lambda state=state, b_est=b_est, bias_se=bias_se: discontinuity_bias(
                state.Dh, state.Dh2, state.passes, b_est, bias_se, *edge_quantiles(state.passes)))
            lum = state.photon_radiance() @ np.array([0.2126, 0.7152, 0.0722])
            known = (state.H > 0) & (state.D > 0)
            dark = (state.H > 0) & ~known

            def never_lit(state: Any = state, lum: np.ndarray = lum, known: np.ndarray = known,
                          dark: np.ndarray = dark, settings: Any = settings) -> list[np.ndarray]:
                scale = unlit_scale(state, lum, known, settings.confidence)
                return [unlit_bound(state, scale, blk) for blk in blocks(len(lum)) if dark[blk].any()]
            _, unlit_cpu = _cpu(never_lit)
            _, estimate_cpu = _cpu(record.integrator.estimate, state)
            per_round.append({
                "round": r, "batches": batches, "checkpoint": folded.checkpointed, "fold_cpu_seconds": fold_cpu,
                "redis_cpu_seconds": redis_cpu,
                "fold_wall_seconds": fold_wall,
                "merge_cpu_seconds": push_cpu / batches, "merge_redis_cpu_seconds": push_redis_cpu / batches,
                "stages": stages, "error": folded.error,
                "image_read": {"state from cache": read_cpu, "image": image_cpu},
                "estimate_parts": {"radius": radius_cpu, "bias estimate": bias_cpu,
                                   "discontinuity bias": edge_cpu, "never-lit bound": unlit_cpu,
                                   "whole estimate": estimate_cpu}})
            print(f"{w}x{h} round {r} ({'checkpoint' if folded.checkpointed else 'memory'}): {fold_wall:.2f} s, "
                  f"folder {fold_cpu:.2f} CPU s, redis {redis_cpu:.2f} CPU s; a batch's merge: worker "
                  f"{push_cpu / batches:.2f} CPU s, redis {push_redis_cpu / batches:.2f} CPU s; "
                  + ", ".join(f"{k} {v:.3f}" for k, v in stages.items()), flush=True)
            # Nothing here holds the folded state into the next round, as in the API between
            # reads: the round then adds to the overlay's state in place (worker/store/overlay.py).
            folded = state = None
        store.delete(job_id)
    finally:
        server.stop()
    def summary(later: list[dict]) -> dict:
        def mean(get) -> float:
            return statistics.fmean(get(x) for x in later)
        return {
            "rounds": len(later),
            "fold_wall_seconds": mean(lambda x: x["fold_wall_seconds"]),
            "fold_cpu_seconds": mean(lambda x: x["fold_cpu_seconds"]),
            "redis_cpu_seconds": mean(lambda x: x["redis_cpu_seconds"]),
            "merge_cpu_seconds": mean(lambda x: x["merge_cpu_seconds"]),
            "merge_redis_cpu_seconds": mean(lambda x: x["merge_redis_cpu_seconds"]),
            "stages": {k: mean(lambda x, k=k: x["stages"].get(k, 0.0))  # (a round may write no state)
                       for k in dict.fromkeys(k for x in later for k in x["stages"])},
            "image_read": {k: mean(lambda x, k=k: x["image_read"][k]) for k in later[0]["image_read"]},
            "estimate_parts": {k: mean(lambda x, k=k: x["estimate_parts"][k]) for k in later[0]["estimate_parts"]}}
    later = per_round[1:] or per_round
    by_kind = {kind: [x for x in later if x["checkpoint"] == (kind == "checkpoint")]
               for kind in ("memory", "checkpoint")}
    return {"width": w, "height": h, "rounds": per_round, "mean_after_first": summary(later),
            "mean_after_first_by_kind": {kind: summary(xs) for kind, xs in by_kind.items() if xs}}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", default="1920x1080,3840x2160", help="comma-separated frame sizes WxH")
    parser.add_argument("--rounds", type=int, default=5, help="fold rounds per size (the first is reported apart)")
    parser.add_argument("--batches", type=int, default=2, help="batches folded per round")
    parser.add_argument("--checkpoint-every", type=int, default=3,
                        help="every K-th round writes the state to the tiles (1: every round, as before overlays)")
    parser.add_argument("--name", default="fold_round", help="bench/out/NAME.json")
    parser.add_argument("--malloc", choices=("retain", "default"), default="retain",
                        help="this process's C heap as the API's (worker/allocator.py), or glibc's defaults")
    args = parser.parse_args()
    if args.malloc == "retain":
        retain_large_allocations()
    try:
        sizes = [tuple(int(v) for v in size.split("x")) for size in args.sizes.split(",")]
    except ValueError:
        parser.error(f"--sizes: expected WxH[,WxH...], got {args.sizes!r}")
    reports = []
    with tempfile.TemporaryDirectory() as tmp:
        for w, h in sizes:
            report = run(w, h, args.rounds, args.batches, args.checkpoint_every, Path(tmp) / f"{w}x{h}")
            reports.append(report)
            for kind, s in [("all", report["mean_after_first"]), *report["mean_after_first_by_kind"].items()]:
                print(f"{w}x{h}, {kind} rounds after the first ({s['rounds']}): {s['fold_wall_seconds']:.2f} s, "
                      f"folder {s['fold_cpu_seconds']:.2f} "
                      f"CPU s, redis {s['redis_cpu_seconds']:.2f} CPU s; a batch's merge: worker "
                      f"{s['merge_cpu_seconds']:.2f} CPU s, redis {s['merge_redis_cpu_seconds']:.2f} CPU s", flush=True)
                for group in ("stages", "image_read", "estimate_parts"):
                    print(f"  {group}: " + ", ".join(f"{k} {v:.3f}" for k, v in s[group].items()), flush=True)
    write_json(args.name, {"batches_per_round": args.batches, "passes_per_batch": PASSES_PER_BATCH,
                           "sizes": reports})


if __name__ == "__main__":
    main()
