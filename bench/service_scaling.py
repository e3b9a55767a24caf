"""Service scaling: one job's photons per second with 1, 2 and 4 workers against the
in-process engine, the merge overhead, HTTP polling latency while jobs render, and the
cost of one merge against image size (where a single Redis stops scaling).

    python -m bench.service_scaling [--full]

Every configuration renders the same job (scene, resolution, photons per pass, seed) for
the same wall time, in this one run. Workers split the machine's cores between them with
POCL_MAX_PTHREAD_COUNT, as `photonfarm serve` does. Each cluster first renders a short
warm-up job so that kernel compilation is not timed. Writes bench/out/service_scaling.json
and bench/out/service_scaling.png.
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import redis

from api_tests.cluster import Cluster, finished
from bench.common import bench_engine, save_figure, write_json
from service.redis_server import EmbeddedRedis
from worker.integrators.base import Delta
from worker.render_loop import render
from worker.settings import Settings
from worker.store import Batch, Jobs, keys

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
                    delta = Delta(k, 1, 1, sums={name: rng.random(layout.zeros(n, name).shape) for name in layout.names})
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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--full", action="store_true", help="512x512 and 40 s per configuration")
    args = parser.parse_args()
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
