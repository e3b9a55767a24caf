"""The hybrid integrator (`method: vcm`) through the real service: workers render its
batches, the store merges its sums exactly once, and the error estimate stops a threshold
job with its actual error at or below the threshold."""

from __future__ import annotations

import json

import numpy as np

from api_tests.cluster import Cluster, finished, merged_passes
from api_tests.helpers import decode_image
from tests.analytic import FURNACE_L
from worker.error_estimate import FLOOR_FRACTION, LUMINANCE
from worker.scene import bundled_scene_path


def test_vcm_job_merges_every_pass_once(cluster: Cluster) -> None:
    p = 4096
    job = cluster.submit(scene_name="furnace", settings={"method": "vcm", "max_passes": 24, "photons_per_pass": p,
                                                          "seed": 2})
    done = cluster.wait(job["id"], finished, timeout=240)
    assert done["status"] == "completed", done
    assert done["passes"] == 24 and done["photons"] == 24 * p
    assert merged_passes(cluster.redis_client, job["id"]) == list(range(24))
    rgb = decode_image(cluster.http.get(job["links"]["image_exr"]).content, ".exr")
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
    # Each pass merged once and counted. Not a prefix of the pass order: the fold that
    # converges the job drops a batch still in flight, and a later one may have come first.
    passes = merged_passes(cluster.redis_client, job["id"])
    assert sorted(set(passes)) == passes and len(passes) == done["passes"]
    assert done["photons"] == done["passes"] * 4096
    lum = decode_image(cluster.http.get(job["links"]["image_exr"]).content, ".exr").reshape(-1, 3) @ LUMINANCE
    actual = np.mean(np.abs(lum - FURNACE_L) / np.maximum(FURNACE_L, FLOOR_FRACTION * FURNACE_L))
    assert actual <= threshold, (actual, done["error_estimate"])


def test_every_method_takes_a_scene_with_a_lens(cluster: Cluster) -> None:
    """A thin lens in every method (camera paths leave from the lens, light tracing projects
    through it): jobs complete with the furnace's radiance in every pixel (the lens changes
    nothing in a uniformly lit sphere), within 10% per pixel mean."""
    scene = json.loads(bundled_scene_path("furnace").read_text())
    scene["camera"]["aperture_radius"] = 0.05
    for method in ("sppm", "vcm", "bpt", "lt"):
        job = cluster.submit(scene=scene, settings={"method": method, "max_passes": 4, "resolution": [16, 16]})
        assert cluster.wait(job["id"], finished)["status"] == "completed", method
        lum = decode_image(cluster.http.get(job["links"]["image_exr"]).content, ".exr") @ LUMINANCE
        assert abs(lum.mean() / FURNACE_L - 1.0) < 0.1, (method, lum.mean())
