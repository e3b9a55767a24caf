"""The hybrid integrator (`method: vcm`) through the real service: workers render its
batches, the store merges its sums exactly once, and the error estimate stops a threshold
job with its actual error at or below the threshold."""

from __future__ import annotations

import numpy as np

from api_tests.cluster import Cluster, finished, merged_passes
from api_tests.test_jobs import _decode
from tests.analytic import FURNACE_L
from worker.error_estimate import FLOOR_FRACTION, LUMINANCE


def test_vcm_job_merges_every_pass_once(cluster: Cluster) -> None:
    p = 4096
    job = cluster.submit(scene_name="furnace", settings={"method": "vcm", "max_passes": 24, "photons_per_pass": p,
                                                          "seed": 2})
    done = cluster.wait(job["id"], finished, timeout=240)
    assert done["status"] == "completed", done
    assert done["passes"] == 24 and done["photons"] == 24 * p
    assert merged_passes(cluster.redis_client, job["id"]) == list(range(24))
    rgb = _decode(cluster.http.get(job["links"]["image_exr"]).content, ".exr")
    assert rgb.shape == (64, 64, 3)
    assert abs(rgb.mean() / FURNACE_L - 1.0) < 0.02, rgb.mean()
    assert 0.0 < done["error_estimate"]["error"] < 1.0


def test_vcm_threshold_job_converges_below_its_threshold(cluster: Cluster) -> None:
    threshold = 0.08
    job = cluster.submit(scene_name="furnace", settings={"method": "vcm", "error_threshold": threshold,
                                                          "photons_per_pass": 4096, "max_seconds": 240, "seed": 4})
    done = cluster.wait(job["id"], finished, timeout=300)
    assert done["status"] == "converged", done
    assert done["error_estimate"]["error"] <= threshold
    assert merged_passes(cluster.redis_client, job["id"]) == list(range(done["passes"]))
    lum = _decode(cluster.http.get(job["links"]["image_exr"]).content, ".exr").reshape(-1, 3) @ LUMINANCE
    actual = np.mean(np.abs(lum - FURNACE_L) / np.maximum(FURNACE_L, FLOOR_FRACTION * FURNACE_L))
    assert actual <= threshold, (actual, done["error_estimate"])
