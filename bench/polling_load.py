"""Polling load: what 20 clients following a job cost the render (issue 10, item 13).

    python -m bench.polling_load [--seconds 30] [--pollers 20] [--interval 1.0]

A real cluster (service/local_cluster.py: redis-server, one worker per core, the API
under uvicorn) renders one cornell-caustics 128x128 job for the same wall time, first
with nobody polling, then with N pollers, each looping over GET the job, GET its PNG and
GET /metrics and then sleeping `--interval` seconds (1 s is what the web viewer does; 0
polls as fast as the API answers), then with nobody polling again (the spread of the two
quiet runs is the noise of the machine). Throughput is the job view's photons per second.
The pollers run in this process, so their own CPU is counted against the render too, as
it would be for clients on the same host. Writes bench/out/polling_load.json and .png.
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import threading
import time
from pathlib import Path

import httpx
import numpy as np

from service.local_cluster import Cluster, finished
from service.models import JobSettings

OUT = Path(__file__).resolve().parent / "out"
SCENE = "cornell-caustics"
RESOLUTION = [128, 128]
PHOTONS = JobSettings().photons_per_pass  # the service's default
CORES = os.cpu_count() or 1
ROUTES = ("job", "image_png", "metrics")


def _percentiles(samples: list[float]) -> dict:
    arr = np.array(samples or [float("nan")]) * 1000.0
    return {"n": len(samples), "p50_ms": float(np.percentile(arr, 50)), "p99_ms": float(np.percentile(arr, 99))}


def run(c: Cluster, seconds: float, pollers: int, interval: float, seed: int) -> dict:
    """One job rendered for `seconds` while `pollers` clients follow it."""
    job = c.submit(scene_name=SCENE, settings={"max_seconds": seconds, "photons_per_pass": PHOTONS,
                                                "resolution": RESOLUTION, "seed": seed})
    c.wait(job["id"], lambda j: j["passes"] >= 1, timeout=120)  # rendering: start polling now
    latencies: dict[str, list[float]] = {route: [] for route in ROUTES}
    stop = threading.Event()
    urls = {"job": job["links"]["self"], "image_png": job["links"]["image_png"], "metrics": "/metrics"}

    def poll() -> None:
        with httpx.Client(base_url=str(c.http.base_url), headers=c.http.headers, timeout=60) as http:
            while not stop.is_set():
                for route in ROUTES:
                    t0 = time.perf_counter()
                    http.get(urls[route]).raise_for_status()
                    latencies[route].append(time.perf_counter() - t0)
                stop.wait(interval)

    threads = [threading.Thread(target=poll, daemon=True) for _ in range(pollers)]
    for t in threads:
        t.start()
    done = c.wait(job["id"], finished, timeout=seconds + 300)
    stop.set()
    for t in threads:
        t.join()
    return {"pollers": pollers, "interval_s": interval if pollers else None, "passes": done["passes"],
            "photons": done["photons"], "elapsed_seconds": done["elapsed_seconds"],
            "photons_per_second": done["photons_per_second"],
            "latency": {route: _percentiles(latencies[route]) for route in ROUTES} if pollers else None}


def chart(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5))
    runs = result["runs"]
    labels = [r["label"] for r in runs]
    axes[0].bar(labels, [r["photons_per_second"] / 1e3 for r in runs], color="#4477aa")
    for i, r in enumerate(runs):
        axes[0].text(i, r["photons_per_second"] / 1e3, f"{r['photons_per_second'] / 1e3:.0f}k", ha="center",
                     va="bottom", fontsize=8)
    axes[0].set_ylabel("k photon paths / s (job view)")
    axes[0].set_title(f"{SCENE} {RESOLUTION[0]}x{RESOLUTION[1]}, {result['workers']} workers, {CORES} cores")
    axes[0].tick_params(axis="x", labelsize=8)
    polled = [r for r in runs if r["pollers"]]
    width = 0.8 / max(1, 2 * len(polled))
    x = np.arange(len(ROUTES))
    for k, r in enumerate(polled):
        for j, q in enumerate(("p50_ms", "p99_ms")):
            axes[1].bar(x + (2 * k + j) * width, [r["latency"][route][q] for route in ROUTES], width,
                        label=f"{r['label']} {q[:3]}")
    axes[1].set_xticks(x + width * (len(polled) - 0.5), ROUTES)
    axes[1].set_yscale("log")
    axes[1].set_ylabel("ms")
    axes[1].set_title("latency per route under polling")
    axes[1].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=30.0, help="render time per configuration")
    parser.add_argument("--pollers", type=int, default=20)
    parser.add_argument("--interval", type=float, nargs="+", default=[1.0, 0.0],
                        help="seconds each poller sleeps between rounds (one polled run per value)")
    args = parser.parse_args()
    runs = []
    with tempfile.TemporaryDirectory() as tmp:
        c = Cluster(Path(tmp), workers=CORES, threads_per_worker=1)
        try:
            warm = c.submit(scene_name=SCENE, settings={"max_passes": 2 * CORES, "photons_per_pass": 1 << 12,
                                                         "resolution": RESOLUTION})
            c.wait(warm["id"], finished, timeout=300)  # kernels compiled before anything is timed
            plan = [("quiet", 0, 0.0)] + [(f"{args.pollers} pollers, {i:g} s", args.pollers, i)
                                          for i in args.interval] + [("quiet again", 0, 0.0)]
            for label, pollers, interval in plan:
                r = run(c, args.seconds, pollers, interval, seed=1)
                r["label"] = label
                runs.append(r)
                print(f"{label:>22}: {r['photons_per_second'] / 1e3:8.1f} k photons/s"
                      + ("".join(f"  {k} p50 {v['p50_ms']:.1f} p99 {v['p99_ms']:.1f} ms"
                                 for k, v in r["latency"].items()) if r["latency"] else ""), flush=True)
        finally:
            c.close()
    quiet = [r["photons_per_second"] for r in runs if not r["pollers"]]
    baseline = float(np.mean(quiet))
    for r in runs:
        r["loss_vs_quiet_mean"] = 1.0 - r["photons_per_second"] / baseline
    result = {"scene": SCENE, "resolution": RESOLUTION, "photons_per_pass": PHOTONS, "seconds": args.seconds,
              "cores": CORES, "workers": CORES, "quiet_spread": (max(quiet) - min(quiet)) / baseline, "runs": runs}
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "polling_load.json").write_text(json.dumps(result, indent=2))
    chart(result, OUT / "polling_load.png")


if __name__ == "__main__":
    main()
