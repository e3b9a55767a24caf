"""The merge path's capacity beyond this machine, by simulation.

Processes stand in for N workers of one job. Each simulated worker renders a batch for as
long as a real worker of the given speed would (it waits), then pushes a real-sized delta
to the job's tiles and has it accepted, as worker/tasks.py does (Jobs.merge without the
encoding: every simulated worker pushes the same pre-encoded delta, random numbers in
every sum of the default SPPM layout, encoded as every delta is (worker/store/tiles.py: the
photon sums float16, the error estimator's float32), so nothing compresses; the encoding's
CPU time is measured once and added to each merge). One folder process folds every
fold_poll_seconds, as the API's folder thread does. Against one Redis and against 3 state
nodes, all redis-servers of the embedded default (service/redis_server.py: append-only file,
fsync always).

The worker's speed: a pass takes trace + seconds-per-megapixel x megapixels (the defaults
stand for a one-thread worker on furnace with the service's default 2^18 photons a pass;
--trace-seconds and --seconds-per-megapixel set them), a batch the passes the scheduler's
own rule gives for that pass time, the mean merge so far, the job's last fold round and
the N workers (worker/store/policy.py batch_passes: a merge and the fold round it causes
at most 5% of the batch and the job's merges at most half the merge path's time, as far
as the N workers together still bring a batch every 10 s, and each delivered at most
9.5 s after the job's other batches due before it, so that deliveries spread: the job's
due set, as Jobs.allocate reads it). Workers start staggered over one batch.

Per frame size, node count and N: merge seconds (push + accept + encode; median, p95),
its share of the simulated workers' time, the passes a batch needs for the mean merge to
be 5% of it, the refresh interval (the seconds between one fold round's end and the
next's while batches arrive: how often the image a client reads changes, as
bench/refresh.py measures it; largest and median), each accepted batch's wait until a
fold round that started after it ended (when the image holds it; largest and median),
and the fold backlog when the workers stop. N is sustained when the merge took at most 5%
of the simulated workers' time and the backlog at the end is at most N batches (the folder
keeps up); the refresh interval is
reported beside it.

Every process here shares this machine's 2 cores, so the direct runs stop short of what the
merge path carries when the state nodes and the folder have cores of their own. The report's
`projected` part estimates that from what the runs measured (`project`): each server's and
the folder's CPU seconds a batch and the merge alone, at the scheduler's batch for each N. It
is a model calibrated here, not a run of N workers.

    python -m bench.merge_capacity --smoke   # a few minutes: small frames, N up to 2
    python -m bench.merge_capacity           # the real run: 1920x1080 and 3840x2160, N to 100
    python -m bench.merge_capacity --sizes 1920x1080   # one frame size of it
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import statistics
import tempfile
import time
from itertools import pairwise
from pathlib import Path
from typing import Any

import numpy as np
import redis

from bench.common import cpu_seconds, save_figure, write_json
from service.redis_server import EmbeddedRedis
from worker.allocator import retain_large_allocations
from worker.config import config
from worker.integrators.base import Delta
from worker.settings import Settings
from worker.store import Batch, Jobs, keys
from worker.store.overlay import OVERLAYS
from worker.store.policy import batch_passes, fold_interval
from worker.store.tiles import encode_delta

PROJECTED_LOAD = 0.7  # a server or the folder busier than this is saturated (project)
ROUND_MODEL_SPAN = 3  # _round_model needs rounds of at least this many times the fewest batches
ROUND_FIXED_POINT_STEPS = 200  # project: damped steps to the batch and round of an N
PROJECTED_WORKERS = (1, 2, 5, 10, 20, 50, 100, 200, 500, 1000)  # charted
PROJECTED_MAX = 1000  # the most workers project tries
FULL = {"sizes": [(1920, 1080), (3840, 2160)], "workers": [1, 2, 5, 10, 20, 50, 100], "batches": 3}
SMOKE = {"sizes": [(320, 180), (640, 360)], "workers": [1, 2], "batches": 2}


def _store(urls: list[str]) -> Jobs:
    return Jobs(redis.Redis.from_url(urls[0]), [redis.Redis.from_url(u) for u in urls[1:]] or None)


def _delta(store: Jobs, job_id: str) -> tuple[Delta, dict[int, bytes], float]:
    """A real-sized random delta, its tiles' payloads, and the seconds encoding them took."""
    record = store.get(job_id)
    layout, n = record.integrator.sums, record.n_pixels
    rng = np.random.default_rng(1)
    delta = Delta(0, 1, 1, {name: rng.random(layout.zeros(n, name).shape) for name in layout.names})
    tiling = store.tiling(record)
    t0 = time.perf_counter()
    payloads = {k: encode_delta(delta.sums, tiling.span(k), layout.half) for k in range(tiling.count)}
    return delta, payloads, time.perf_counter() - t0


def _merge(store: Jobs, job_id: str, batch: Batch, delta: Delta, payloads: dict[int, bytes]) -> None:
    record = store.get(job_id)
    store.tiles.push_encoded(job_id, store.tiling(record), batch.id, payloads.__getitem__)
    header = Delta(batch.first, batch.n, batch.n, {})
    assert store.accept(batch, header, 1.0, 1.0)[0] == "merged"


def _steady_batch(pass_seconds: float, mean_merge: float, fold_seconds: float, n_workers: int) -> float:
    """Seconds of the scheduler's batch once the N workers' deliveries are spread (the
    others due every refresh_seconds: Jobs.allocate's rule in its steady state)."""
    spread = [i * config().refresh_seconds for i in range(1, n_workers)]
    return batch_passes(pass_seconds, mean_merge, None, fold_seconds, n_workers, others_due=spread) * pass_seconds


def _next_batch(store: Jobs, job_id: str, worker: int, pass_seconds: float, mean_merge: float,
                n_workers: int) -> float:
    """A simulated worker's next batch, sized as Jobs.allocate sizes it: with the job's last
    fold round and the other workers' expected deliveries (the job's due set, where each
    simulated worker keeps its own), so that their deliveries spread as the service's do."""
    now, me = time.time(), f"sim-{worker}".encode()
    others = [due - now for member, due in store.r.zrange(keys.due(job_id), 0, -1, withscores=True) if member != me]
    seconds = batch_passes(pass_seconds, mean_merge, None, store.get(job_id).fold_seconds, n_workers,
                           others_due=others) * pass_seconds
    store.r.zadd(keys.due(job_id), {me: now + seconds + mean_merge})
    return seconds


def _pusher(urls: list[str], job_id: str, workers: list[int], n_workers: int, pass_seconds: float,
            first_merge: float, first: float, start: float, end: float, first_batch: int, out: mp.Queue) -> None:
    """Simulated workers `workers` (of n_workers): render a batch (the first `first` seconds,
    as run calibrated it; wait), push, accept, repeat; each next batch sized by the
    scheduler's rule from the mean merge so far and the others' deliveries (_next_batch)."""
    retain_large_allocations()  # as `photonfarm worker` does
    store = _store(urls)
    delta, payloads, encode = _delta(store, job_id)
    due = {w: start + first * (1 + w / n_workers) for w in workers}
    store.r.zadd(keys.due(job_id), {f"sim-{w}": at + first_merge for w, at in due.items()})
    latencies, lateness, accepted, rendered, batch_no = [first_merge], [], [], 0.0, first_batch
    while True:
        w = min(due, key=due.get)
        if due[w] > end:
            break
        time.sleep(max(0.0, due[w] - time.time()))
        lateness.append(time.time() - due[w])
        t0 = time.perf_counter()
        _merge(store, job_id, Batch(job_id, batch_no, 1), delta, payloads)
        latencies.append(time.perf_counter() - t0 + encode)
        accepted.append(time.time())
        batch_no += 1
        batch = _next_batch(store, job_id, w, pass_seconds, statistics.fmean(latencies), n_workers)
        rendered += batch
        due[w] = time.time() + batch
    out.put({"latencies": latencies[1:], "lateness": lateness, "accepted": accepted, "rendered": rendered})


def _folder(urls: list[str], job_id: str, pushed: Any, out: mp.Queue) -> None:
    """The API's folder thread: every fold_poll_seconds, a round if one is due, until the
    simulated workers are done (`pushed`) and everything they had accepted is folded. Each
    round's start and end, and the backlog when the workers stopped (did it keep up?)."""
    retain_large_allocations()  # as `photonfarm serve` does
    store = _store(urls)
    rounds, costs, backlog, cpu0 = [], [], None, time.process_time()

    def unfolded() -> int:  # accepted batches not in the image yet
        return len({b.decode() for b in store.r.hkeys(keys.tofold(job_id))} - OVERLAYS.batches(job_id))
    while backlog is None or unfolded():
        t0 = time.time()
        if backlog is None and pushed.is_set():
            backlog = unfolded()
        waiting, cpu = unfolded(), time.process_time()
        if store.fold_if_due(job_id) is not None:
            rounds.append((t0, time.time()))
            costs.append((waiting, time.process_time() - cpu))
        time.sleep(max(0.0, config().fold_poll_seconds - (time.time() - t0)))
    store.fold(job_id, wait=True, checkpoint=True)  # as the job's end does
    out.put({"rounds": rounds, "costs": costs, "backlog": backlog, "cpu_seconds": time.process_time() - cpu0})


def _round_model(costs: list[tuple[int, float]]) -> tuple[float, float] | None:
    """A round's CPU seconds as a + b * (batches it folds), least squares over the rounds
    (a: the whole-state merge, estimate and checkpoint; b: reading and adding a delta);
    None unless the rounds' batch counts span a factor ROUND_MODEL_SPAN (rounds of one
    or two batches each cannot tell a round's part from a delta's)."""
    counts = [n for n, _ in costs]
    if not counts or max(counts) < ROUND_MODEL_SPAN * min(counts):
        return None
    b, a = np.polyfit([n for n, _ in costs], [c for _, c in costs], 1)
    return float(max(a, 0.0)), float(max(b, 0.0))


def _image_lags(accepted: list[float], rounds: list[tuple[float, float]]) -> list[float]:
    """Per accepted batch, seconds until the end of the first fold round that started
    after it (the batch is in the image then); inf if none did."""
    return [min((end - t for start, end in rounds if start >= t), default=float("inf")) for t in accepted]


def _job(store: Jobs, w: int, h: int) -> str:
    job_id = store.create({}, Settings(max_passes=10 ** 7), w, h, None)
    store.init_setup(store.get(job_id), {"R0": np.ones(w * h)})
    store.r.hset(keys.job(job_id), mapping={"status": "running", "started": time.time()})
    return job_id


def run(urls: list[str], pids: list[int], w: int, h: int, n_workers: int, pass_seconds: float, batches: int,
        processes: int) -> dict:
    store = _store(urls)
    # Calibrate: one merge alone gives the scheduler's batch size.
    job_id = _job(store, w, h)
    delta, payloads, encode = _delta(store, job_id)
    t0 = time.perf_counter()
    _merge(store, job_id, Batch(job_id, 0, 1), delta, payloads)
    alone = time.perf_counter() - t0 + encode
    store.fold(job_id, wait=True)  # the job's first round: its length sizes the batches (Jobs.allocate)
    batch_seconds = _steady_batch(pass_seconds, alone, store.get(job_id).fold_seconds, n_workers)
    # Run N workers and the folder for `batches` batches each.
    ctx = mp.get_context("spawn")
    out: mp.Queue = ctx.Queue()
    start = time.time() + 5.0  # the pushers build their deltas meanwhile
    end = start + batch_seconds * (batches + 1)
    groups = [list(range(p, n_workers, processes)) for p in range(min(processes, n_workers))]
    procs = [ctx.Process(target=_pusher, args=(urls, job_id, g, n_workers, pass_seconds, alone, batch_seconds,
                                               start, end, 1 + i * 10 ** 6, out)) for i, g in enumerate(groups)]
    pushed = ctx.Event()
    procs.append(ctx.Process(target=_folder, args=(urls, job_id, pushed, out)))
    node_cpu0 = [cpu_seconds([pid]) for pid in pids]
    for p in procs:
        p.start()
    pushes = [out.get() for _ in groups]
    pushed.set()
    fold = out.get()
    for p in procs:
        p.join()
    node_cpu = [cpu_seconds([pid]) - c for pid, c in zip(pids, node_cpu0, strict=True)]
    latencies = sorted(x for r in pushes for x in r["latencies"])
    accepted = [t for r in pushes for t in r["accepted"]]
    lags = _image_lags(accepted, fold["rounds"]) or [float("inf")]
    # The image changes at each round's end; between the first and the last batch accepted.
    ends = [e for _, e in fold["rounds"]]
    first, last = min(accepted, default=0.0), max(accepted, default=0.0)
    while_busy = [e for e in ends if first <= e <= last] + [min((e for e in ends if e > last), default=float("inf"))]
    refresh = [b - a for a, b in pairwise(while_busy)] or [float("inf")]
    p95 = latencies[int(0.95 * (len(latencies) - 1))] if latencies else float("nan")
    record = store.get(job_id)
    assert record.passes == 1 + len(latencies), "a merge was lost or counted twice"
    assert record.folded_passes == record.passes, "the folder left accepted batches unfolded"
    report = {"width": w, "height": h, "nodes": len(urls) - 1 or 1, "workers": n_workers,
              "pass_seconds": pass_seconds, "first_batch_seconds": batch_seconds,
              "merge_alone_seconds": alone, "encode_seconds": encode, "merges": len(latencies),
              "merge_median_seconds": statistics.median(latencies) if latencies else None,
              "merge_p95_seconds": p95,
              "share": sum(latencies) / (sum(latencies) + sum(r["rendered"] for r in pushes)) if latencies else None,
              "needed_batch_passes": (statistics.fmean(latencies) / config().merge_share / pass_seconds
                                      if latencies else None),
              "lateness_max_seconds": max((x for r in pushes for x in r["lateness"]), default=0.0),
              "refresh_max_seconds": max(refresh), "refresh_median_seconds": statistics.median(refresh),
              "image_lag_max_seconds": max(lags), "image_lag_median_seconds": statistics.median(lags),
              "fold_rounds": len(fold["rounds"]),
              "fold_round_median_seconds": statistics.median(e - s for s, e in fold["rounds"])
              if fold["rounds"] else None,
              "backlog_at_end": fold["backlog"],
              # CPU seconds a batch, pushes, folds and checkpoints included: the main Redis
              # (the record, the queue) and each state node, and the folder
              "node_cpu_per_batch": [c / len(latencies) for c in node_cpu] if latencies else None,
              "folder_cpu_per_batch": fold["cpu_seconds"] / len(latencies) if latencies else None,
              "folder_round_costs": fold["costs"], "folder_round_model": _round_model(fold["costs"]),
              "delta_bytes": sum(len(p) for p in payloads.values())}
    report["sustained"] = bool(latencies and report["share"] <= config().merge_share
                               and report["backlog_at_end"] <= n_workers)
    store.delete(job_id)
    return report


def project(runs: list[dict]) -> dict:
    """Beyond this machine: each server and the folder on a core of its own. From the
    largest N a series sustained here, the CPU seconds a batch costs the main Redis, each
    state node and the folder (pushes, folds and checkpoints), and the merge alone. The
    folder's rounds come at most every fold_interval (plus the round), each folding every
    batch accepted meanwhile: its load is the rounds a second times a round's fixed cost plus
    the batches a second times a delta's (_round_model over every round of the series; the
    CPU seconds a batch at the largest N sustained, which spread a round over that N's
    batches, is kept as `folder_per_batch_load_at_100`). For each N the scheduler's batch,
    sized by the merge and the round that round model gives at that N (`steady`), gives the
    rate batches arrive, N / (batch + merge), and with it each part's load; the merge waits
    longer on a loaded node (as on a queue served at random: alone / (1 - load)). A part is
    saturated at PROJECTED_LOAD. Reported per series: the largest N up to PROJECTED_MAX
    whose every part stays below that with the merge under 5%, what limits the next N, and
    the loads, batch and round at N = 100."""
    out = {}
    for (w, h, nodes), series in _series(runs).items():
        done = [r for r in series if r["sustained"]]
        if not done:
            continue
        base = done[-1]
        costs = {"main redis" if nodes > 1 else "redis": base["node_cpu_per_batch"][0],
                 **{f"state node {i}": c for i, c in enumerate(base["node_cpu_per_batch"][1:], 1)},
                 "folder": base["folder_cpu_per_batch"]}
        merge, pass_seconds = base["merge_alone_seconds"], base["pass_seconds"]
        round_seconds = base["fold_round_median_seconds"] or 0.0
        model = _round_model([tuple(c) for r in series for c in r.get("folder_round_costs", [])])

        def steady(n: int, round_seconds: float = round_seconds, pass_seconds: float = pass_seconds,
                   merge: float = merge, model: tuple[float, float] | None = model) -> tuple[float, float, float]:
            """The batch, the batches a second and the fold round at N = n. The scheduler's
            batch takes the job's last round, and with the folder on a core of its own a
            round lasts its CPU seconds (the model), which grow with the batches it folds:
            the fixed point of the two (a round measured here, at the base N on shared
            cores, would stand for every N)."""
            length = round_seconds
            for _ in range(ROUND_FIXED_POINT_STEPS):
                batch = _steady_batch(pass_seconds, merge, length, n)
                rate = n / (batch + merge)
                if model is None:
                    break
                period = fold_interval(length) + config().fold_poll_seconds / 2 + length
                length = 0.5 * (length + model[0] + model[1] * max(1.0, rate * period))
            return batch, rate, length

        def loads(n: int, costs: dict[str, float] = costs, merge: float = merge,
                  model: tuple[float, float] | None = model) -> tuple[dict[str, float], float, float]:
            """Each part's load, the merge share and the batches a second, at N = n."""
            batch, rate, length = steady(n)
            load = {part: rate * c for part, c in costs.items()}
            if model is not None:
                rounds = min(rate, 1.0 / (fold_interval(length) + config().fold_poll_seconds / 2 + length))
                load["folder"] = rounds * model[0] + rate * model[1]
            waited = merge / max(1e-9, 1.0 - max(load.values()))
            return load, waited / (batch + waited), rate

        def limit_at(n: int) -> str | None:
            """What N = n overloads (None if nothing): a part, or the merge share (a few
            workers' batches, held to the refresh, can give the merge more than 5%)."""
            load, share, _ = loads(n)
            if max(load.values()) > PROJECTED_LOAD:
                return max(load, key=load.get)
            return "merge share" if share > config().merge_share else None

        capacity = max((n for n in range(1, PROJECTED_MAX + 1) if limit_at(n) is None), default=0)
        limit = limit_at(capacity + 1)
        at_100, share_100, rate_100 = loads(100)
        out[f"{w}x{h}, {nodes} node(s)"] = {
            "busiest_part_by_workers": {n: max(loads(n)[0].values()) for n in PROJECTED_WORKERS},
            "from_workers": base["workers"], "cpu_seconds_per_batch": costs, "merge_alone_seconds": merge,
            "capacity": capacity, "limited_by": limit, "loads_at_100": at_100, "merge_share_at_100": share_100,
            "folder_round_model": model, "folder_per_batch_load_at_100": rate_100 * costs["folder"],
            "bytes_per_second_at_100": rate_100 * base["delta_bytes"],
            "batch_and_round_seconds_at_100": steady(100)[::2]}
    return out


def chart(report: dict, name: str) -> None:
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(17, 4.5))
    for (w, h, nodes), runs in _series(report["runs"]).items():
        label = f"{w}x{h}, {nodes} node{'s' if nodes > 1 else ''}"
        xs = [r["workers"] for r in runs]
        axes[0].plot(xs, [r["needed_batch_passes"] for r in runs], "o-", label=label)
        axes[1].plot(xs, [r["refresh_max_seconds"] for r in runs], "o-", label=label)
        busiest = report["projected"].get(f"{w}x{h}, {nodes} node(s)", {}).get("busiest_part_by_workers", {})
        axes[2].plot([int(n) for n in busiest], list(busiest.values()), "o-", label=label)
    axes[1].axhline(config().refresh_seconds, color="grey", ls="--", label="10 s")
    axes[2].axhline(PROJECTED_LOAD, color="grey", ls="--", label="saturated")
    for ax, title in zip(axes, ("passes a batch needs for the merge to take 5%", "refresh interval, largest (s)",
                                "projected: the busiest server or folder, a core each"), strict=True):
        if any(min(line.get_xdata(), default=0) > 0 for line in ax.lines):  # (no projection: nothing sustained)
            ax.set_xscale("log")
        ax.set_xlabel("simulated workers")
        ax.set_title(title)
        ax.legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, name)


def _series(runs: list[dict]) -> dict[tuple[int, int, int], list[dict]]:
    out: dict[tuple[int, int, int], list[dict]] = {}
    for r in runs:
        out.setdefault((r["width"], r["height"], r["nodes"]), []).append(r)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--smoke", action="store_true", help="small frames and few workers: checks the bench runs")
    parser.add_argument("--seconds-per-megapixel", type=float, default=0.49,
                        help="a pass's per-pixel cost (eye, gather, readback, host) per megapixel")
    parser.add_argument("--trace-seconds", type=float, default=0.15, help="a pass's photon tracing")
    parser.add_argument("--processes", type=int, default=8, help="pusher processes the simulated workers share")
    parser.add_argument("--sizes", help="comma-separated frame sizes WxH instead of the plan's (e.g. 1920x1080)")
    parser.add_argument("--workers", help="comma-separated N instead of the plan's (e.g. 1,10,20)")
    parser.add_argument("--nodes", default="1,3", help="comma-separated state node counts (1: the one Redis)")
    parser.add_argument("--name", help="bench/out/NAME.json and .png (default: merge_capacity, or _smoke)")
    args = parser.parse_args()
    plan = SMOKE if args.smoke else FULL
    if args.sizes:
        try:
            plan = {**plan, "sizes": [tuple(int(v) for v in size.split("x")) for size in args.sizes.split(",")]}
        except ValueError:
            parser.error(f"--sizes: expected WxH[,WxH...], got {args.sizes!r}")
    if args.workers:
        try:
            plan = {**plan, "workers": [int(n) for n in args.workers.split(",")]}
        except ValueError:
            parser.error(f"--workers: expected N[,N...], got {args.workers!r}")
    try:
        node_counts = [int(v) for v in args.nodes.split(",")]
    except ValueError:
        parser.error(f"--nodes: expected N[,N...], got {args.nodes!r}")
    runs = []
    with tempfile.TemporaryDirectory() as tmp:
        for n_nodes in node_counts:
            servers = [EmbeddedRedis(Path(tmp) / f"{n_nodes}-{i}", maxmemory="0").start(supervise=False)
                       for i in range(1 + (n_nodes if n_nodes > 1 else 0))]
            urls = [s.url for s in servers]
            try:
                for w, h in plan["sizes"]:
                    pass_seconds = args.trace_seconds + args.seconds_per_megapixel * w * h / 1e6
                    for n in plan["workers"]:
                        r = run(urls, [s.proc.pid for s in servers], w, h, n, pass_seconds, plan["batches"],
                                args.processes)
                        runs.append(r)
                        print(f"{w}x{h} nodes={r['nodes']} workers={n}: merge p95 {r['merge_p95_seconds']:.3f} s, "
                              f"share {100 * r['share']:.2f}%, batch needs {r['needed_batch_passes']:.1f} passes, "
                              f"batch {r['first_batch_seconds']:.0f} s, refresh max {r['refresh_max_seconds']:.1f} s "
                              f"(a batch in the image after {r['image_lag_max_seconds']:.1f} s at most), "
                              f"backlog {r['backlog_at_end']}, sustained {r['sustained']}", flush=True)
                        # A larger N only loads the folder and the nodes more: stop once it
                        # falls behind, or fails after a smaller N was sustained (a small N can
                        # fail alone: the scheduler shortens its batches for the refresh).
                        if not r["sustained"] and (r["backlog_at_end"] > n
                                                   or any(x["sustained"] for x in runs[:-1]
                                                          if (x["width"], x["height"], x["nodes"])
                                                          == (w, h, r["nodes"]))):
                            break
            finally:
                for s in servers:
                    s.stop()
    capacity = {f"{w}x{h}, {nodes} node(s)": max((r["workers"] for r in rs if r["sustained"]), default=0)
                for (w, h, nodes), rs in _series(runs).items()}
    projected = project(runs)
    report = {"smoke": args.smoke, "seconds_per_megapixel": args.seconds_per_megapixel,
              "trace_seconds": args.trace_seconds, "capacity": capacity, "projected": projected, "runs": runs}
    name = args.name or ("merge_capacity_smoke" if args.smoke else "merge_capacity")
    write_json(name, report)
    chart(report, name)
    print(capacity)
    for series, p in projected.items():
        print(f"projected, {series}, each part on a core of its own: {p['capacity']} workers "
              f"(limited by {p['limited_by']}); at 100 workers: "
              + ", ".join(f"{part} {load:.0%}" for part, load in p["loads_at_100"].items())
              + f", merge share {p['merge_share_at_100']:.1%}, {p['bytes_per_second_at_100'] / 1e6:.0f} MB/s of deltas")


if __name__ == "__main__":
    main()
