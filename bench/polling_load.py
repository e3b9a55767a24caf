"""Polling load: what 20 clients following a job cost the render.

    python -m bench.polling_load [--seconds 30] [--pollers 20] [--interval 1.0 0.0] [--rounds 2]

A real cluster (api_tests/cluster.py: redis-server, one worker per core, the API
under uvicorn) renders one cornell-caustics 128x128 job for the same wall time, first
with nobody polling, then with N pollers, each looping over GET the job, GET its PNG (with
If-None-Match naming the ETag it last got, as a browser's cache does) and GET /metrics and then
sleeping `--interval` seconds (1 s is what the web viewer does; 0
polls as fast as the API answers); `--rounds` repeats that sequence, so that load from
other processes on the host falls on every configuration alike. Throughput is the job
view's merge history: photons per second between the first and last merge of the window,
which opens at the job's first merge. On a shared host that figure moves with everything else
running, so each run also records the CPU seconds of every process (API, workers, Redis,
and this process, whose threads are the pollers): the API's and the pollers' share of the
machine is what polling takes from the workers, whatever else the host runs. Writes
bench/out/polling_load.json and .png.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import threading
import time
from pathlib import Path

import httpx
import numpy as np

from api_tests.cluster import Cluster, finished
from bench.common import cpu_seconds, save_figure, write_json
from service.models import JobSettings

SCENE = "cornell-caustics"
RESOLUTION = [128, 128]
PHOTONS = JobSettings(method="sppm").for_frame(*RESOLUTION).paths_per_pass  # the default for sppm
CORES = os.cpu_count() or 1
ROUTES = ("job", "image_png", "metrics")


def _percentiles(samples: list[float]) -> dict:
    arr = np.array(samples or [float("nan")]) * 1000.0
    return {"n": len(samples), "p50_ms": float(np.percentile(arr, 50)), "p99_ms": float(np.percentile(arr, 99))}


def _throughput(history: list[dict], t0: float, t1: float) -> tuple[float, int]:
    """Photons per second between the first and the last merge inside [t0, t1] (job seconds)."""
    inside = [h for h in history if t0 <= h["seconds"] <= t1]
    if len(inside) < 2:
        return float("nan"), len(inside)
    first, last = inside[0], inside[-1]
    return (last["photons"] - first["photons"]) / (last["seconds"] - first["seconds"]), len(inside)


def run(c: Cluster, seconds: float, pollers: int, interval: float, seed: int) -> dict:
    """A job rendered while `pollers` clients follow it for `seconds`, from its first merge on
    (so the job's start-up, eye pass and initial radius, is not in the window)."""
    job = c.submit(scene_name=SCENE, settings={"max_seconds": 10 * seconds + 600, "photons_per_pass": PHOTONS,
                                                "resolution": RESOLUTION, "seed": seed})
    start = c.wait(job["id"], lambda j: j["passes"] >= 1, timeout=600)
    parts = {"api": [c.api.pid], "workers": [w.pid for w in c.workers], "redis": [c.redis.proc.pid],
             "pollers": [os.getpid()]}
    cpu0, wall0 = {k: cpu_seconds(v) for k, v in parts.items()}, time.perf_counter()
    latencies: dict[str, list[float]] = {route: [] for route in ROUTES}
    stop = threading.Event()
    urls = {"job": job["links"]["self"], "image_png": job["links"]["image_png"], "metrics": "/metrics"}

    def poll() -> None:
        tags: dict[str, str] = {}  # the last ETag of each route, sent back as a browser's cache does
        with httpx.Client(base_url=str(c.http.base_url), headers=c.http.headers, timeout=60) as http:
            while not stop.is_set():
                for route in ROUTES:
                    t0 = time.perf_counter()
                    resp = http.get(urls[route], headers={"If-None-Match": tags[route]} if route in tags else {})
                    if resp.status_code != 304:
                        resp.raise_for_status()
                    if "ETag" in resp.headers:
                        tags[route] = resp.headers["ETag"]
                    latencies[route].append(time.perf_counter() - t0)
                stop.wait(interval)

    threads = [threading.Thread(target=poll, daemon=True) for _ in range(pollers)]
    for t in threads:
        t.start()
    time.sleep(seconds)
    stop.set()
    for t in threads:
        t.join()
    wall = time.perf_counter() - wall0
    cpu = {k: cpu_seconds(v) - cpu0[k] for k, v in parts.items()}
    end = c.job(job["id"])
    c.http.delete(job["links"]["self"]).raise_for_status()
    c.wait(job["id"], finished, timeout=600)
    rate, merges = _throughput(end["error_history"], start["elapsed_seconds"], end["elapsed_seconds"])
    return {"pollers": pollers, "interval_s": interval if pollers else None, "window_seconds": wall,
            "merges_in_window": merges, "photons_per_second": rate,
            # the workers' own speed: unchanged by polling unless the API slows what they do
            "photons_per_worker_cpu_second": rate * wall / cpu["workers"],
            # each part's CPU as a share of the machine (cores x wall time) during the window
            "cpu_share": {k: v / (CORES * wall) for k, v in cpu.items()},
            "latency": {route: _percentiles(latencies[route]) for route in ROUTES} if pollers else None}


def chart(result: dict) -> None:
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(17, 4.8))
    runs = result["runs"]
    names = [f"{r['label']}\n(round {r['round'] + 1})" for r in runs]
    x = np.arange(len(runs))
    axes[0].bar(x, [r["photons_per_second"] / 1e3 for r in runs], color="#4477aa")
    for i, r in enumerate(runs):
        axes[0].text(i, r["photons_per_second"] / 1e3, f"{r['photons_per_second'] / 1e3:.0f}k", ha="center",
                     va="bottom", fontsize=8)
    axes[0].set_xticks(x, names, fontsize=7, rotation=30, ha="right")
    axes[0].set_ylabel("k photon paths / s (job view)")
    axes[0].set_title(f"{SCENE} {RESOLUTION[0]}x{RESOLUTION[1]}, {result['workers']} workers, "
                      f"{CORES} cores (shared host)", fontsize=9)
    bottom = np.zeros(len(runs))
    for part, colour in (("workers", "#4477aa"), ("api", "#cc6677"), ("pollers", "#ddcc77"), ("redis", "#228833")):
        share = np.array([100 * r["cpu_share"][part] for r in runs])
        axes[1].bar(x, share, bottom=bottom, color=colour, label=part)
        bottom += share
    axes[1].set_xticks(x, names, fontsize=7, rotation=30, ha="right")
    axes[1].set_ylabel("% of the machine's CPU while rendering")
    axes[1].set_title("where the CPU went (the rest: other processes on the host)", fontsize=9)
    axes[1].legend(fontsize=8)
    polled = [r for r in runs if r["pollers"] and r["round"] == runs[-1]["round"]]
    width = 0.8 / max(1, 2 * len(polled))
    xr = np.arange(len(ROUTES))
    for k, r in enumerate(polled):
        for j, q in enumerate(("p50_ms", "p99_ms")):
            axes[2].bar(xr + (2 * k + j) * width, [r["latency"][route][q] for route in ROUTES], width,
                        label=f"{r['label']} {q[:3]}")
    axes[2].set_xticks(xr + width * (len(polled) - 0.5), ROUTES)
    axes[2].set_yscale("log")
    axes[2].set_ylabel("ms")
    axes[2].set_title("latency per route under polling (last round)", fontsize=9)
    axes[2].legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, "polling_load")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=30.0, help="render time per configuration")
    parser.add_argument("--pollers", type=int, default=20)
    parser.add_argument("--interval", type=float, nargs="+", default=[1.0, 0.0],
                        help="seconds each poller sleeps between rounds (one polled run per value)")
    parser.add_argument("--rounds", type=int, default=2, help="times the whole sequence runs")
    args = parser.parse_args()
    runs = []
    with tempfile.TemporaryDirectory() as tmp:
        c = Cluster(Path(tmp), workers=CORES, threads_per_worker=1)
        try:
            warm = c.submit(scene_name=SCENE, settings={"max_passes": 2 * CORES, "photons_per_pass": 1 << 12,
                                                         "resolution": RESOLUTION})
            c.wait(warm["id"], finished, timeout=300)  # kernels compiled before anything is timed
            plan = [("quiet", 0, 0.0)] + [(f"{args.pollers} pollers, {i:g} s", args.pollers, i)
                                          for i in args.interval]
            for round_ in range(args.rounds):
                for label, pollers, interval in plan:
                    r = run(c, args.seconds, pollers, interval, seed=1)
                    r["label"], r["round"] = label, round_
                    runs.append(r)
                    shares = " ".join(f"{k} {100 * v:.1f}%" for k, v in r["cpu_share"].items())
                    print(f"{label:>22}: {r['photons_per_second'] / 1e3:8.1f} k photons/s "
                          f"({r['photons_per_worker_cpu_second'] / 1e3:.1f} k per worker CPU s)  cpu: {shares}"
                          + ("".join(f"  {k} p50 {v['p50_ms']:.1f} p99 {v['p99_ms']:.1f} ms"
                                     for k, v in r["latency"].items()) if r["latency"] else ""), flush=True)
        finally:
            c.close()
    quiet = [r["photons_per_second"] for r in runs if not r["pollers"]]
    baseline = float(np.mean(quiet))
    summary = {}
    for label, _, _ in plan:
        same = [r for r in runs if r["label"] == label]
        summary[label] = {"photons_per_second_mean": float(np.mean([r["photons_per_second"] for r in same])),
                          "loss_vs_quiet": 1.0 - float(np.mean([r["photons_per_second"] for r in same])) / baseline,
                          "api_plus_pollers_cpu_share": float(np.mean([r["cpu_share"]["api"] + r["cpu_share"]["pollers"]
                                                                       for r in same]))}
    result = {"scene": SCENE, "resolution": RESOLUTION, "photons_per_pass": PHOTONS, "seconds": args.seconds,
              "cores": CORES, "workers": CORES, "quiet_spread": (max(quiet) - min(quiet)) / baseline,
              "host_load_average": os.getloadavg(), "summary": summary, "runs": runs}
    for label, v in summary.items():
        print(f"{label:>22}: mean {v['photons_per_second_mean'] / 1e3:.1f} k photons/s, "
              f"loss {100 * v['loss_vs_quiet']:.1f}% against quiet, "
              f"API + pollers {100 * v['api_plus_pollers_cpu_share']:.1f}% "
              f"of the machine", flush=True)
    write_json("polling_load", result)
    chart(result)


if __name__ == "__main__":
    main()
