"""Termination at an error threshold, the reported estimate and its history, and the error
map, over real HTTP. On the analytic scenes the actual error is known exactly."""

from __future__ import annotations

import tempfile
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from api_tests.cluster import Cluster, finished
from api_tests.helpers import decode_image
from tests.analytic import FURNACE_L, point_plane
from worker.error_estimate import FLOOR_FRACTION, LUMINANCE
from worker.image_io import read_channels
from worker.scene import bundled_scene_path, load_scene_file
from worker.scene_arrays import compile_scene


def _truth(scene: str) -> np.ndarray:
    if scene == "furnace":
        return np.full(64 * 64, FURNACE_L)
    parsed, base = load_scene_file(bundled_scene_path(scene))
    return point_plane(SimpleNamespace(arrays=compile_scene(parsed, base)))[0]


@pytest.mark.parametrize("scene", ["furnace", "point-plane"])
def test_job_converges_and_its_actual_error_is_below_the_threshold(cluster: Cluster, scene: str) -> None:
    threshold = 0.08
    job = cluster.submit(scene_name=scene, settings={"error_threshold": threshold, "confidence": 0.9,
                                                      "photons_per_pass": 1 << 15, "max_seconds": 240, "seed": 4})
    done = cluster.wait(job["id"], finished, timeout=300)
    assert done["status"] == "converged", done
    assert done["error_estimate"]["error"] <= threshold
    history = done["error_history"]
    assert [h["passes"] for h in history] == sorted(h["passes"] for h in history)
    assert history[-1]["passes"] == done["passes"] and history[0]["error"] > threshold
    est = decode_image(cluster.http.get(job["links"]["image_exr"]).content, ".exr").reshape(-1, 3) @ LUMINANCE
    truth = _truth(scene)
    floor = FLOOR_FRACTION * truth.mean()  # the same policy the estimate uses
    actual = np.mean(np.abs(est - truth) / np.maximum(truth, floor))
    assert actual <= threshold, (actual, done["error_estimate"])


def test_error_map_png_and_exr(cluster: Cluster) -> None:
    job = cluster.submit(scene_name="cornell-caustics", settings={"max_passes": 6, "photons_per_pass": 1 << 14,
                                                                  "resolution": [40, 30]})
    assert cluster.http.get(job["links"]["error_png"]).status_code in (200, 409)  # 409 before the first merge
    done = cluster.wait(job["id"], finished)
    png = cluster.http.get(job["links"]["error_png"])
    assert png.status_code == 200 and png.headers["content-type"] == "image/png"
    colours = decode_image(png.content, ".png")
    assert colours.shape == (30, 40, 3) and colours.std() > 0.0
    exr = cluster.http.get(job["links"]["error_exr"])
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "error.exr"
        path.write_bytes(exr.content)
        ch = read_channels(path)
    assert set(ch) == {"bias", "noise", "bound", "relative"} and ch["bound"].shape == (30, 40)
    assert all(np.all(np.isfinite(c)) for c in ch.values())
    assert np.all(ch["noise"] >= 0) and np.all(ch["bound"] >= ch["noise"] - 1e-6)
    assert np.all(ch["bound"] <= ch["noise"] + np.abs(ch["bias"]) + 1e-6)
    assert float(exr.headers["x-average-relative-error"]) == pytest.approx(done["error_estimate"]["error"], rel=1e-3)
