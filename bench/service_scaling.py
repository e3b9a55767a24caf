"""Service scaling: one job's photons per second with 1, 2 and 4 workers against the
in-process engine, the merge overhead, HTTP polling latency while jobs render, and the
cost of one merge against image size (where a single Redis stops scaling); with
`--pinned`, the scaling of one-thread workers pinned to their cores.

    python -m bench.service_scaling [--full]
    python -m bench.service_scaling --pinned [--smoke]

Every configuration renders the same job (scene, resolution, photons per pass, seed) for
the same wall time, in this one run. Workers split the machine's cores between them with
POCL_MAX_PTHREAD_COUNT, as `photonfarm serve` does. Each cluster first renders a short
warm-up job so that kernel compilation is not timed. Writes bench/out/service_scaling.json
and bench/out/service_scaling.png.

`--pinned`: a real cluster with 1, then 2 workers, each with one PoCL thread
and pinned to its own core (taskset), renders one furnace job at 256x256 and one at
1920x1080 (the service's default photons per pass, error estimation on). Both jobs of a frame size render the
same fixed passes (same seed): the time to the end is the job's wall time from submission
to its final status (start-up included, as a user waits for it), and the photons per
second are measured between the job's first and last accepted batch. Equal work matters:
an SPPM pass gets cheaper as its radius shrinks, so a job that got further in a fixed
time would look faster than it is. The radius per pass still depends somewhat on how
passes were grouped into fold rounds (worker/stats.py), so the two jobs end at somewhat
different errors; the time to a fixed error (the larger final error, from each job's
error history) is reported too. The 2-worker / 1-worker ratios of all three, each of the
means of two runs per configuration taken in the order 1, 2, 2, 1 workers (PINNED_ORDER):
the machine's speed drifts over the minutes a run takes, and with the two runs of a
configuration placed symmetrically in time a drift linear in time falls out of the ratio,
where one 1-worker run followed by one 2-worker run minutes later carried all of it. The API (with its folder
thread) and redis-server are not pinned: this machine has no third core, so wherever
they ran they would take from a worker; unpinned, the kernel puts them on whichever
core is idle at the moment (a one-worker job leaves a core free for them, as a real
deployment with one worker per core does not). Every process's CPU seconds over the
job (psutil; Redis with its append-only-file rewrites) are split per accepted batch:
the workers' rendering and merging (push and accept, from the job record), the API
(the folder's rounds) and Redis. CPU seconds move far less with the shared machine's
load than wall time, and say what keeps the ratio below 2x. Per job also the host's
share (bench.common.host_seconds): each core's steal time (the hypervisor running other
guests while this VM wanted the core; a pinned worker then renders slower whatever we do)
and the CPU of processes other than the cluster's. `--smoke` runs small frames
for a few seconds (a check that it runs). Writes bench/out/service_scaling_pinned.json
and .png (`_smoke` for the smoke run).
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import statistics
import tempfile
import threading
import time
from dataclasses import dataclass
from itertools import pairwise
from pathlib import Path

import numpy as np
import redis

from api_tests.cluster import Cluster, finished
from bench.common import bench_engine, core_times, cpu_seconds, host_seconds, save_figure, write_json
from service.redis_server import EmbeddedRedis
from worker.integrators.base import Delta
from worker.render_loop import render
from worker.settings import Settings
from worker.store import Batch, Jobs, keys
from worker.store.policy import FINAL

SCENE = "cornell-caustics"
CORES = os.cpu_count() or 1


def in_process(resolution: tuple[int, int], photons: int, seconds: float) -> dict:
    engine = bench_engine(SCENE, resolution, photons_per_pass=photons, seed=1)
    state = render(engine, passes=1)  # warm-up
    start = time.perf_counter()
    render(engine, seconds=seconds, state=state)
    elapsed = time.perf_counter() - start
    return {"config": "in-process", "passes": state.passes - 1,
            "photons_per_second": (state.passes - 1) * photons / elapsed}


def _percentiles(samples: list[float]) -> dict:
    arr = np.array(samples) * 1000.0
    return {"n": len(samples), "p50_ms": float(np.percentile(arr, 50)), "p99_ms": float(np.percentile(arr, 99)),
            "max_ms": float(arr.max())}


def on_cluster(workers: int, resolution: tuple[int, int], photons: int, seconds: float, poll: bool) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        c = Cluster(Path(tmp), workers=workers, threads_per_worker=max(1, CORES // workers))
        try:
            warm = c.submit(scene_name=SCENE, settings={"max_passes": 2 * workers, "photons_per_pass": 1 << 12,
                                                         "resolution": list(resolution)})
            c.wait(warm["id"], finished, timeout=300)
            job = c.submit(scene_name=SCENE, settings={"max_seconds": seconds, "photons_per_pass": photons,
                                                        "resolution": list(resolution), "seed": 1})
            status_lat: list[float] = []
            image_lat: list[float] = []
            stop = threading.Event()

            def poller() -> None:
                n = 0
                while not stop.is_set():
                    t0 = time.perf_counter()
                    c.http.get(f"/v1/jobs/{job['id']}").raise_for_status()
                    status_lat.append(time.perf_counter() - t0)
                    n += 1
                    if n % 10 == 0:
                        t0 = time.perf_counter()
                        c.http.get(f"/v1/jobs/{job['id']}/image", params={"format": "png"}).raise_for_status()
                        image_lat.append(time.perf_counter() - t0)
                    time.sleep(0.05)

            thread = threading.Thread(target=poller, daemon=True)
            if poll:
                thread.start()
            done = c.wait(job["id"], finished, timeout=seconds + 300)
            stop.set()
            record = Jobs(c.redis_client).get(job["id"])
            render_s, merge_s = record.render_seconds, record.merge_seconds
            out = {"config": f"{workers} worker{'s' if workers > 1 else ''}", "workers": workers,
                   "passes": done["passes"], "merges": record.merges,
                   "photons_per_second": done["photons"] / done["elapsed_seconds"],
                   "merge_seconds": merge_s, "render_seconds": render_s,
                   # per worker, the share of its time spent merging rather than rendering
                   "merge_overhead": merge_s / (render_s + merge_s)}
            if poll:
                out["poll_status"] = _percentiles(status_lat)
                out["poll_image_png"] = _percentiles(image_lat)
            return out
        finally:
            c.close()


def merge_cost(sizes: list[tuple[int, int]], repeats: int = 5) -> list[dict]:
    """Seconds per merge of one batch into a job of each size, on the embedded Redis."""
    rng = np.random.default_rng(0)
    out = []
    with tempfile.TemporaryDirectory() as tmp:
        server = EmbeddedRedis(Path(tmp) / "redis").start(supervise=False)
        try:
            store = Jobs(redis.Redis.from_url(server.url))
            for w, h in sizes:
                n = w * h
                job_id = store.create({}, Settings(max_passes=1000), w, h, None)
                record = store.get(job_id)
                store.init_setup(record, {"R0": np.ones(n)})
                store.r.hset(keys.job(job_id), mapping={"status": "running", "started": time.time()})
                layout = record.integrator.sums
                state_bytes = 8 * n * sum(record.integrator.state_widths.values())
                times = []
                for k in range(repeats):
                    delta = Delta(k, 1, 1,
                                  sums={name: rng.random(layout.zeros(n, name).shape) for name in layout.names})
                    t0 = time.perf_counter()
                    assert store.merge(Batch(job_id, k, 1), delta, 1.0) == "merged"
                    times.append(time.perf_counter() - t0)
                out.append({"width": w, "height": h, "pixels": n, "state_mb": state_bytes / 1e6,
                            "merge_seconds": statistics.median(times)})
                store.r.delete(*store.r.keys(f"pf:job:{job_id}*"))
        finally:
            server.stop()
    return out


def chart(result: dict) -> None:
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(15, 4.5))
    runs = result["throughput"]
    axes[0].bar([r["config"] for r in runs], [r["photons_per_second"] / 1e6 for r in runs], color="#4477aa")
    for i, r in enumerate(runs):
        label = f"{r['photons_per_second'] / 1e6:.2f}"
        if "merge_overhead" in r:
            label += f"\nmerge {100 * r['merge_overhead']:.1f}%"
        axes[0].text(i, r["photons_per_second"] / 1e6, label, ha="center", va="bottom", fontsize=8)
    axes[0].set_ylabel("M photon paths / s")
    axes[0].set_title(f"one job, {result['scene']} {result['resolution'][0]}x{result['resolution'][1]}")
    p = result["polling"]
    if p:
        names = ["GET job p50", "GET job p99", "GET png p50", "GET png p99"]
        vals = [p["poll_status"]["p50_ms"], p["poll_status"]["p99_ms"], p["poll_image_png"]["p50_ms"],
                p["poll_image_png"]["p99_ms"]]
        axes[1].bar(names, vals, color="#cc6677")
        axes[1].set_ylabel("ms")
        axes[1].set_title(f"polling latency while rendering ({p['config']})")
        axes[1].tick_params(axis="x", labelsize=8)
    mc = result["merge_cost"]
    axes[2].loglog([m["pixels"] for m in mc], [m["merge_seconds"] for m in mc], "o-", color="#228833")
    axes[2].axhline(0.05 * 2.0, ls="--", color="grey", label="5% of a 2 s batch")
    axes[2].set_xlabel("pixels")
    axes[2].set_ylabel("seconds per merge")
    axes[2].set_title("one merge against image size")
    axes[2].legend()
    fig.tight_layout()
    save_figure(fig, "service_scaling")


# ------------------------------------------------------ pinned one-thread workers
@dataclass(frozen=True)
class PinnedCase:
    """One frame size of the pinned measurement: the passes each job renders."""

    resolution: tuple[int, int]
    passes: int


PINNED_SCENE = "furnace"
PINNED = (PinnedCase((256, 256), 100), PinnedCase((1920, 1080), 80))
PINNED_ORDER = (1, 2, 2, 1)  # workers of the clusters, in turn (the module docstring says why)
PINNED_SMOKE = (PinnedCase((128, 128), 12), PinnedCase((320, 180), 8))
SAMPLE_SECONDS = 0.25  # how often the job record's photon count is read during a job


def _window_rate(samples: list[tuple[float, int]]) -> float:
    """Photons per second between the job's first accepted batch and its last (the job's
    start-up, engine build and the first batch's set-up pass, left out)."""
    first = next(((t, e) for t, e in samples if e > 0), None)
    last = next(((t, e) for t, e in samples if e == samples[-1][1]), None)
    if first is None or last[0] <= first[0]:
        return float("nan")
    return (last[1] - first[1]) / (last[0] - first[0])


def _pinned_job(c: Cluster, case: PinnedCase, workers: int) -> dict:
    """One job on the running cluster, its rate, time to the error and every process's CPU."""
    jobs = Jobs(c.redis_client)
    parts = {"workers": [w.pid for w in c.workers], "api": [c.api.pid], "redis": [c.redis.proc.pid]}
    load = os.getloadavg()[0]
    cpu0, cores0, wall0 = {k: cpu_seconds(v) for k, v in parts.items()}, core_times(), time.perf_counter()
    job_id = c.submit(scene_name=PINNED_SCENE, settings={"max_passes": case.passes,
                                                         "resolution": list(case.resolution),
                                                  "seed": 1})["id"]
    samples: list[tuple[float, int]] = []
    while True:
        record = jobs.get(job_id)
        samples.append((time.perf_counter(), record.emitted))
        if record.status in FINAL:  # final only once every accepted batch is folded
            break
        time.sleep(SAMPLE_SECONDS)
    wall = time.perf_counter() - wall0
    cpu = {k: cpu_seconds(v) - cpu0[k] for k, v in parts.items()}
    host = host_seconds(cores0, core_times(), sum(cpu.values()))
    history = jobs.history(job_id)
    batches, rounds = max(1, record.merges), max(1, len(history))
    split = {"worker render": record.render_cpu_seconds, "worker merge": record.merge_cpu_seconds,
             "worker other": cpu["workers"] - record.render_cpu_seconds - record.merge_cpu_seconds,
             "api": cpu["api"], "redis": cpu["redis"]}
    return {"resolution": list(case.resolution), "workers": workers, "status": record.status.value,
            "wall_seconds": wall, "elapsed_seconds": record.elapsed_seconds(),
            "passes": record.passes, "batches": record.merges, "fold_rounds": len(history),
            "photons": record.emitted, "photons_per_second": _window_rate(samples),
            "photons_per_second_whole_job": record.photons_per_second,
            "time_to_error": wall, "final_error": history[-1]["error"] if history else None,
            "render_seconds_per_pass": record.render_seconds / max(1, record.passes),
            "cpu_seconds": split, "cpu_seconds_per_batch": {k: v / batches for k, v in split.items()},
            "api_cpu_seconds_per_fold_round": cpu["api"] / rounds,
            "load_average_before": load, "load_average_after": os.getloadavg()[0],
            "host": host, "history": history}


def pinned(workers: int, cases: tuple[PinnedCase, ...]) -> list[dict]:
    """Every case on one cluster of `workers` one-thread workers, worker i pinned to core i."""
    with tempfile.TemporaryDirectory() as tmp:
        c = Cluster(Path(tmp), workers=0, threads_per_worker=1, redis_maxmemory="4gb")
        try:
            for core in range(workers):
                c.start_worker(prefix=["taskset", "-c", str(core % CORES)])
            warm = c.submit(scene_name=PINNED_SCENE, settings={"max_passes": 2 * workers,
                                                                "photons_per_pass": 1 << 12, "resolution": [64, 64]})
            c.wait(warm["id"], finished, timeout=600)  # kernels built in every worker before anything is timed
            out = []
            for case in cases:
                run = _pinned_job(c, case, workers)
                out.append(run)
                tte = run["time_to_error"]
                print(f"{workers} worker(s) {case.resolution[0]}x{case.resolution[1]}: "
                      f"{run['photons_per_second'] / 1e6:.3f} M photons/s "
                      f"(whole job {run['photons_per_second_whole_job'] / 1e6:.3f}), "
                      f"error {run['final_error']:.4f} after {tte:.1f} s, "
                      f"{run['batches']} batches, {run['fold_rounds']} folds, load {run['load_average_before']:.1f}, "
                      f"steal {sum(run['host']['steal_seconds']):.2f} s, "
                      f"others {run['host']['others_cpu_seconds']:.2f} CPU s; "
                      "CPU s per batch: " + ", ".join(f"{k} {v:.2f}" for k, v in run["cpu_seconds_per_batch"].items()),
                      flush=True)
            return out
        finally:
            c.close()


def _seconds_to_error(run: dict, error: float) -> float | None:
    """Job seconds until the estimated error first fell to `error` (between two fold rounds:
    linear in log error), from the job's history; None if it never did."""
    h = [(e["seconds"], e["error"]) for e in run["history"] if e["error"] is not None]
    for (t0, e0), (t1, e1) in pairwise([(0.0, float("inf")), *h]):
        if e1 <= error:
            if not np.isfinite(e0) or e0 <= e1:
                return t1
            return t0 + (t1 - t0) * float(np.log(e0 / error) / np.log(e0 / e1))
    return None


def _mean(values: list[float | None]) -> float | None:
    return statistics.fmean(values) if values and all(v is not None for v in values) else None


def _ratios(runs: list[dict]) -> list[dict]:
    """Per frame size, 2 workers against 1, from the means of each configuration's runs:
    photons per second, time to the end (the same passes: 1w / 2w) and time to a fixed
    error (the largest of the runs' final errors; SPPM's radius, and so the error at equal
    passes, depends on how passes were grouped into fold rounds, worker/stats.py)."""
    out = []
    for size in dict.fromkeys(tuple(r["resolution"]) for r in runs):
        one, two = ([r for r in runs if tuple(r["resolution"]) == size and r["workers"] == w] for w in (1, 2))
        error = max(r["final_error"] or 0.0 for r in one + two)
        means = {w: {k: _mean([r[k] for r in rs]) for k in ("photons_per_second", "photons_per_second_whole_job",
                                                              "time_to_error")}
                 | {"fixed": _mean([_seconds_to_error(r, error) for r in rs])} for w, rs in ((1, one), (2, two))}
        t1, t2 = means[1]["time_to_error"], means[2]["time_to_error"]
        e1, e2 = means[1]["fixed"], means[2]["fixed"]
        out.append({"resolution": list(size), "runs": [len(one), len(two)],
                    "photons_per_second": means[2]["photons_per_second"] / means[1]["photons_per_second"],
                    "photons_per_second_whole_job": means[2]["photons_per_second_whole_job"]
                    / means[1]["photons_per_second_whole_job"],
                    "time_to_error": t1 / t2 if t1 and t2 else None,
                    "fixed_error": error, "time_to_fixed_error": e1 / e2 if e1 and e2 else None})
    return out


def pinned_chart(result: dict, name: str) -> None:
    import matplotlib.pyplot as plt

    runs, ratios = result["runs"], result["ratios"]
    sizes = [r["resolution"] for r in ratios]
    fig, axes = plt.subplots(1, 3, figsize=(17, 4.8))
    x = np.arange(len(sizes))
    top = 0.0
    for k, workers in enumerate((1, 2)):
        rates = [statistics.fmean(r["photons_per_second"] for r in runs
                                  if r["workers"] == workers and r["resolution"] == s) / 1e6 for s in sizes]
        axes[0].bar(x + 0.4 * k, rates, 0.38, label=f"{workers} worker{'s' * (workers > 1)}")
        top = max(top, *rates)
    for i, q in enumerate(ratios):
        tte = "-" if q["time_to_error"] is None else f"{q['time_to_error']:.2f}x"
        axes[0].text(i + 0.2, top * 1.02, f"2w/1w: {q['photons_per_second']:.2f}x photons/s,\n{tte} time to error",
                     ha="center", va="bottom", fontsize=8)
    axes[0].set_ylim(0, top * 1.25)
    axes[0].set_xticks(x + 0.2, [f"{w}x{h}" for w, h in sizes])
    axes[0].set_ylabel("M photon paths / s")
    axes[0].set_title(f"{PINNED_SCENE}, one-thread workers pinned to a core each ({CORES} cores, shared host)",
                      fontsize=9)
    axes[0].legend(fontsize=8)
    for r in runs:
        h = [e for e in r["history"] if e["error"] is not None]
        axes[1].semilogy([e["seconds"] for e in h], [e["error"] for e in h],
                         "-" if r["workers"] == 1 else "--", label=f"{r['resolution'][0]}x{r['resolution'][1]}, "
                         f"{r['workers']}w")
    axes[1].set_xlabel("job seconds")
    axes[1].set_ylabel("estimated error (image average)")
    axes[1].set_title("the job's error history (both end at the same passes)", fontsize=9)
    axes[1].legend(fontsize=7)
    big = [r for r in runs if r["resolution"] == sizes[-1]]
    bottom = np.zeros(len(big))
    for part, colour in zip(big[0]["cpu_seconds_per_batch"], ("#4477aa", "#66ccee", "#bbbbbb", "#cc6677", "#228833"),
                            strict=False):
        v = np.array([r["cpu_seconds_per_batch"][part] for r in big])
        axes[2].bar(np.arange(len(big)), v, bottom=bottom, color=colour, label=part)
        bottom += v
    axes[2].set_xticks(np.arange(len(big)), [f"{r['workers']} worker{'s' * (r['workers'] > 1)}\n"
                                             f"{r['passes'] / max(1, r['batches']):.1f} passes a batch" for r in big])
    axes[2].set_ylabel("CPU seconds per accepted batch")
    axes[2].set_title(f"where the CPU went at {sizes[-1][0]}x{sizes[-1][1]}", fontsize=9)
    axes[2].set_ylim(0, bottom.max() * 1.45)
    axes[2].legend(fontsize=8, ncol=3, loc="upper center")
    fig.tight_layout()
    save_figure(fig, name)


def pinned_main(smoke: bool) -> None:
    cases = PINNED_SMOKE if smoke else PINNED
    runs = [run for workers in PINNED_ORDER for run in pinned(workers, cases)]
    result = {"scene": PINNED_SCENE, "cores": CORES, "cases": [dataclasses.asdict(c) for c in cases], "runs": runs,
              "ratios": _ratios(runs)}
    name = "service_scaling_pinned" + ("_smoke" if smoke else "")
    write_json(name, result)
    pinned_chart(result, name)
    for q in result["ratios"]:
        tte = "-" if q["time_to_error"] is None else f"{q['time_to_error']:.2f}x"
        fixed = "-" if q["time_to_fixed_error"] is None else f"{q['time_to_fixed_error']:.2f}x"
        print(f"{q['resolution'][0]}x{q['resolution'][1]}: 2 workers / 1: {q['photons_per_second']:.2f}x photons/s "
              f"(whole job {q['photons_per_second_whole_job']:.2f}x), {tte} time to the end (same passes), "
              f"{fixed} time to the error {q['fixed_error']:.4f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--full", action="store_true", help="512x512 and 40 s per configuration")
    parser.add_argument("--pinned", action="store_true",
                        help="1 and 2 one-thread workers, each pinned to a core, at 256x256 and 1920x1080")
    parser.add_argument("--smoke", action="store_true", help="with --pinned: small frames, a few seconds each")
    args = parser.parse_args()
    if args.smoke and not args.pinned:
        parser.error("--smoke needs --pinned")
    if args.pinned:
        return pinned_main(args.smoke)
    resolution = (512, 512) if args.full else (256, 256)
    seconds = 60.0 if args.full else 30.0
    photons = 1 << 18
    runs = [in_process(resolution, photons, seconds)]
    for workers in (1, 2, 4):
        runs.append(on_cluster(workers, resolution, photons, seconds, poll=False))
    # Polling latency on its own run: the poller's own CPU would otherwise slow the throughput runs.
    polled = on_cluster(2, resolution, photons, seconds, poll=True)
    polled["config"] = "2 workers, polled"
    sizes = [(128, 128), (256, 256), (512, 512), (1024, 768), (1280, 1024)]
    result = {"scene": SCENE, "resolution": resolution, "photons_per_pass": photons, "seconds": seconds,
              "cores": CORES, "throughput": runs, "polling": polled, "merge_cost": merge_cost(sizes)}
    write_json("service_scaling", result)
    chart(result)
    for r in runs:
        extra = f"  merge {100 * r['merge_overhead']:.1f}%" if "merge_overhead" in r else ""
        print(f"{r['config']:>12}: {r['photons_per_second'] / 1e6:6.2f} M photons/s{extra}")
    for m in result["merge_cost"]:
        print(f"merge {m['width']}x{m['height']}: {1000 * m['merge_seconds']:.1f} ms")


if __name__ == "__main__":
    main()
