"""Jobs of different sizes and priorities interleave at batch granularity."""

from __future__ import annotations

from api_tests.cluster import Cluster, finished


def test_small_job_is_not_stuck_behind_a_large_one(cluster: Cluster) -> None:
    big = cluster.submit(scene_name="cornell-box", settings={"max_seconds": 900, "photons_per_pass": 1 << 17,
                                                             "resolution": [64, 64]})
    cluster.wait(big["id"], lambda j: j["passes"] >= 2)
    small = cluster.submit(scene_name="furnace", settings={"max_passes": 3, "photons_per_pass": 1 << 12})
    done = cluster.wait(small["id"], finished, timeout=60)
    assert done["status"] == "completed"
    assert cluster.job(big["id"])["status"] == "running"  # the small one finished while the big one ran
    high = cluster.submit(scene_name="furnace", settings={"max_passes": 3, "photons_per_pass": 1 << 12,
                                                          "priority": "high"})
    assert cluster.wait(high["id"], finished, timeout=60)["status"] == "completed"
    assert cluster.job(big["id"])["status"] == "running"
    cluster.http.delete(f"/v1/jobs/{big['id']}")
    assert cluster.wait(big["id"], finished, timeout=30)["status"] == "cancelled"
