"""The service's largest frame, 3840 x 2160, through real HTTP, Redis and workers: the job
completes with exact pass and photon totals, its image is the whole frame, and the bytes
a pixel its state takes in Redis are the ones docs/limits.md states (folded state at most 128: the
float64 arrays each tile holds, an array only where a delta carried it, within a byte a
pixel of Redis's allocation; batch inputs 8, nothing left pending). And a time budget holds
at a large frame: the job ends within its seconds plus one batch (its render, merge and the
final fold)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from api_tests.cluster import Cluster, finished, merged_passes
from api_tests.helpers import decode_image
from service.models import MAX_SERVICE_PIXELS
from worker.store import Jobs

W, H = 3840, 2160
P = 1 << 14
PASSES = 3


def _bytes_per_pixel(c: Cluster, job_id: str, part: str) -> float:
    r = c.redis_client
    return sum(r.memory_usage(k) for k in r.scan_iter(f"pf:job:{job_id}:t*:{part}")) / (W * H)


def _state_bytes_per_pixel(c: Cluster, job_id: str) -> tuple[float, float]:
    """The tiles' states in Redis, bytes a pixel: measured, and the float64 arrays they hold
    (each tile holds R0, N, S, D and H, and every other array only if a delta carried it there)."""
    r = c.redis_client
    widths = Jobs(r).get(job_id).integrator.state_widths
    used = held = 0
    for key in r.scan_iter(f"pf:job:{job_id}:t*:state"):
        fields = {f.decode() for f in r.hkeys(key)}
        assert {"R0", "N", "S", "D", "H"} <= fields, fields
        used += r.memory_usage(key, samples=0)  # every field (the default samples 5)
        held += 8 * (r.hstrlen(key, "R0") // 8) * sum(widths[f] for f in fields)
    return used / (W * H), held / (W * H)


def test_a_3840x2160_job_completes_with_exact_totals(tmp_path: Path) -> None:
    assert W * H == MAX_SERVICE_PIXELS
    c = Cluster(tmp_path, workers=2, redis_maxmemory="6gb")
    try:
        job = c.submit(scene_name="furnace", settings={"resolution": [W, H], "max_passes": PASSES,
                                                        "photons_per_pass": P, "seed": 2})
        done = c.wait(job["id"], finished, timeout=1500)
        assert done["status"] == "completed", done
        assert done["passes"] == PASSES and done["photons"] == PASSES * P, done
        assert merged_passes(c.redis_client, job["id"]) == list(range(PASSES))
        used, held = _state_bytes_per_pixel(c, job["id"])
        assert 8 * 5 <= held <= 136.0 and held <= used < held + 1.0, (used, held)
        assert 12.0 <= _bytes_per_pixel(c, job["id"], "inputs") < 12.5  # radius, N and bias, float32
        assert _bytes_per_pixel(c, job["id"], "pending") == 0.0
        resp = c.http.get(job["links"]["image_exr"])
        assert resp.status_code == 200 and resp.headers["x-passes"] == str(PASSES)
        rgb = decode_image(resp.content, ".exr")
        assert rgb.shape == (H, W, 3) and np.isfinite(rgb).all() and rgb.mean() > 0.0
    finally:
        c.close()


def test_a_time_budget_holds_at_1920x1080(tmp_path: Path) -> None:
    budget = 20.0
    c = Cluster(tmp_path, workers=2, redis_maxmemory="4gb")
    try:
        job = c.submit(scene_name="furnace", settings={"resolution": [1920, 1080], "max_seconds": budget,
                                                        "photons_per_pass": P, "seed": 3})
        done = c.wait(job["id"], finished, timeout=600)
        assert done["status"] == "completed" and done["passes"] >= 2, done
        record = Jobs(c.redis_client).get(job["id"])
        # The last batch was taken before the budget ran out and may be a worker's first (its
        # engine built first): at most the longest batch from lease to push, its accept, and
        # the final move's folds (it waits for a round in progress, then folds the rest).
        one_batch = record.longest_batch_seconds + record.mean_merge_seconds + 2.0 * record.fold_seconds
        assert done["elapsed_seconds"] <= budget + one_batch, (done["elapsed_seconds"], one_batch)
        assert done["photons"] == done["passes"] * P
        # The workers' CPU seconds the record keeps (bench/service_scaling.py --pinned splits them).
        assert 0.0 < record.merge_cpu_seconds < record.render_cpu_seconds, record
    finally:
        c.close()
