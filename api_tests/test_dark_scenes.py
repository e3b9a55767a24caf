"""Scenes that render black: no light at all, light that never reaches what the camera
sees, and nothing at all (no shapes, no lights: the scene has no size). The job must end
(on its budget) with a black image and a defined error estimate: no NaN, no hang, no
failure."""

from __future__ import annotations

import numpy as np
import pytest

from api_tests.cluster import Cluster, finished
from api_tests.helpers import decode_image


def _furnace_variant(cluster: Cluster, dark: str) -> dict:
    scene = cluster.http.get("/v1/scenes/furnace").json()
    if dark == "no light":
        scene["lights"] = []
    elif dark == "nothing":  # no shapes either: the scene is the camera alone
        scene["lights"], scene["shapes"] = [], []
    else:  # the light sits outside the closed sphere the camera looks at: none gets in
        scene["lights"][0]["position"] = [0.0, 0.0, 5.0]
    return scene


@pytest.mark.parametrize("dark", ["no light", "light outside", "nothing"])
def test_black_scene_ends_with_a_black_image_and_a_defined_error(cluster: Cluster, dark: str) -> None:
    job = cluster.submit(scene=_furnace_variant(cluster, dark),
                         settings={"max_passes": 6, "photons_per_pass": 1 << 12, "error_threshold": 0.05})
    done = cluster.wait(job["id"], finished, timeout=60)
    assert done["status"] == "completed" and done["passes"] == 6, done  # the threshold cannot be met
    assert done["error_estimate"]["error"] == 1.0  # nothing was ever lit: the error is unknown, 100%
    rgb = decode_image(cluster.http.get(job["links"]["image_exr"]).content, ".exr")
    assert np.all(np.isfinite(rgb)) and rgb.max() == 0.0
    err = cluster.http.get(job["links"]["error_exr"])
    assert err.status_code == 200 and err.headers["x-average-relative-error"] == "1"


@pytest.mark.parametrize("method", ["ppm", "vcm", "bpt", "lt"])
def test_a_scene_of_nothing_renders_black_with_every_method(cluster: Cluster, method: str) -> None:
    job = cluster.submit(scene=_furnace_variant(cluster, "nothing"),
                         settings={"method": method, "max_passes": 2, "photons_per_pass": 1 << 10})
    done = cluster.wait(job["id"], finished, timeout=60)
    assert done["status"] == "completed" and done["passes"] == 2, done
    rgb = decode_image(cluster.http.get(job["links"]["image_exr"]).content, ".exr")
    assert np.all(np.isfinite(rgb)) and rgb.max() == 0.0
