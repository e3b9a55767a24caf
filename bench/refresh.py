"""How often the image a client sees refreshes on a big job, through the real service (the
service's aim: at least every 10 s on a 3840x2160 job).

A real cluster (api_tests/cluster.py: embedded Redis, the API with its folder thread, RQ
workers with one PoCL thread each) renders one furnace job of the given size for
`--seconds` (the service's default photons per pass, error estimation on). The job record
is read every 0.25 s; each fold round's end (`folded_at`, when the image a client reads
changes if it folded new passes), length (`fold_seconds`) and whether it rebuilt the state
from the tiles (no overlay in the folder's memory: a job's first round, or one after another
process's checkpoint; policy.Round) are noted. Reported: the intervals between image
changes from the first image to the job's end (largest, median), the rounds' lengths, when
each batch was accepted, each round's whole cost (its checkpoint writes after the image
included) and when a Redis server rewrote its append-only file (to a sample), and the API's
(folder) and Redis's CPU seconds per round (every redis-server's: with `--shards N` the
job's state lies on N more servers, PHOTONFARM_STATE_URLS). Wall time on a shared machine:
the load average before and after is in the report.

    python -m bench.refresh                          # 3840x2160, 2 workers, 120 s
    python -m bench.refresh --shards 3               # the same with the state on 3 nodes
    python -m bench.refresh --size 640x360 --seconds 20   # a quick check that it runs
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time
from itertools import pairwise
from pathlib import Path

import redis

from api_tests.cluster import Cluster, finished
from bench.common import cpu_seconds, write_json
from worker.config import config
from worker.store import Jobs
from worker.store.policy import FINAL

SCENE = "furnace"
SAMPLE_SECONDS = 0.25
REWRITE_START_SLACK = 1.5  # seconds: INFO gives a rewrite's age in whole seconds


def run(w: int, h: int, seconds: float, workers: int, shards: int = 0) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        c = Cluster(Path(tmp), workers=workers, threads_per_worker=1, redis_maxmemory="6gb", shards=shards)
        try:
            warm = c.submit(scene_name=SCENE, settings={"max_passes": 2 * workers, "photons_per_pass": 1 << 12,
                                                        "resolution": [64, 64]})
            c.wait(warm["id"], finished, timeout=600)  # kernels built in every worker first
            jobs = Jobs(c.redis_client)
            parts = {"api": [c.api.pid], "redis": [s.proc.pid for s in (c.redis, *c.shards)]}
            load = os.getloadavg()[0]
            cpu0 = {k: cpu_seconds(v) for k, v in parts.items()}
            job_id = c.submit(scene_name=SCENE, settings={"max_seconds": seconds, "resolution": [w, h],
                                                          "seed": 1})["id"]
            rounds: list[dict] = []
            accepted: list[float] = []  # when each batch was accepted (to a sample)
            servers = [redis.Redis.from_url(s.url) for s in (c.redis, *c.shards)]
            rewriting: list[list[float]] = []  # append-only-file rewrites (any server): [start, end]
            current: dict[int, list[float]] = {}  # each server's latest rewrite in `rewriting`
            while True:
                record = jobs.get(job_id)
                now = time.time()
                accepted += [now] * (record.merges - len(accepted))
                for i, server in enumerate(servers):
                    info = server.info("persistence")
                    if info["aof_rewrite_in_progress"]:
                        # A rewrite is known by its server and start (its age in whole seconds),
                        # so one seen in samples that came late (a busy server answers late)
                        # stays one rewrite.
                        start = now - info["aof_current_rewrite_time_sec"]
                        if i not in current or abs(current[i][0] - start) > REWRITE_START_SLACK:
                            current[i] = [start, now]
                            rewriting.append(current[i])
                        current[i][1] = now
                if record.folded_at and (not rounds or record.folded_at != rounds[-1]["end"]):
                    rounds.append({"end": record.folded_at, "seconds": record.fold_seconds,
                                   "passes": record.image_passes,
                                   "rebuilt": bool(record.fold_rounds and record.fold_rounds[-1].rebuilt)})
                if rounds and record.folded_at == rounds[-1]["end"]:
                    # Its whole length, checkpoint writes included (noted after its image);
                    # the folder starts no other round before that ends.
                    rounds[-1]["cost"] = record.round_cost
                if record.status in FINAL:
                    break
                time.sleep(SAMPLE_SECONDS)
            cpu = {k: cpu_seconds(v) - cpu0[k] for k, v in parts.items()}
        finally:
            c.close()
    # The image changes at the end of a round that folded new passes (not at a checkpoint
    # that wrote what the image already held).
    changes = [r for i, r in enumerate(rounds) if i == 0 or r["passes"] != rounds[i - 1]["passes"]]
    intervals = [b["end"] - a["end"] for a, b in pairwise(changes)]
    lengths = [r["seconds"] for r in rounds]
    return {"width": w, "height": h, "workers": workers, "shards": shards, "seconds": seconds,
            "status": record.status.value,
            "passes": record.passes, "batches": record.merges, "fold_rounds": len(rounds),
            "pass_seconds": record.pass_seconds, "merge_seconds_mean": record.mean_merge_seconds,
            "refresh_max_seconds": max(intervals, default=float("nan")),
            "refresh_median_seconds": statistics.median(intervals) if intervals else float("nan"),
            "fold_round_max_seconds": max(lengths, default=float("nan")),
            "fold_round_median_seconds": statistics.median(lengths) if lengths else float("nan"),
            "api_cpu_seconds_per_round": cpu["api"] / max(1, len(rounds)),
            "redis_cpu_seconds_per_round": cpu["redis"] / max(1, len(rounds)),
            "load_average_before": load, "load_average_after": os.getloadavg()[0],
            "rounds": rounds, "intervals": intervals, "accepted": accepted, "aof_rewrites": rewriting,
            "target_seconds": config().refresh_seconds}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--size", default="3840x2160", help="frame size WxH")
    parser.add_argument("--seconds", type=float, default=120.0, help="the job's time budget")
    parser.add_argument("--workers", type=int, default=2, help="workers, one PoCL thread each")
    parser.add_argument("--shards", type=int, default=0, help="state nodes besides the main Redis (0: none)")
    args = parser.parse_args()
    try:
        w, h = (int(v) for v in args.size.split("x"))
    except ValueError:
        parser.error(f"--size: expected WxH, got {args.size!r}")
    report = run(w, h, args.seconds, args.workers, args.shards)
    print(f"{w}x{h}, {args.workers} workers, {args.shards} shards, "
          f"{report['passes']} passes in {report['batches']} batches: "
          f"{report['fold_rounds']} fold rounds, image refreshed every {report['refresh_median_seconds']:.1f} s "
          f"(largest {report['refresh_max_seconds']:.1f} s; target {config().refresh_seconds:.0f} s), rounds "
          f"{report['fold_round_median_seconds']:.1f} s (largest {report['fold_round_max_seconds']:.1f} s); "
          f"CPU s a round: API {report['api_cpu_seconds_per_round']:.2f}, Redis "
          f"{report['redis_cpu_seconds_per_round']:.2f}; load {report['load_average_before']:.1f} to "
          f"{report['load_average_after']:.1f}")
    write_json(f"refresh_{w}x{h}" + (f"_{args.shards}shards" if args.shards else ""), report)


if __name__ == "__main__":
    main()
