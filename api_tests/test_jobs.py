"""Submitting, polling, images, cancelling and bad input, over real HTTP."""

from __future__ import annotations

import threading
from itertools import pairwise
from pathlib import Path

import httpx
import pytest

from api_tests.cluster import Cluster, finished, merged_passes
from api_tests.helpers import decode_image
from service.models import MAX_ACTIVE_JOBS, MAX_BODY_BYTES, MAX_SERVICE_PHOTONS_PER_PASS
from tests.analytic import FURNACE_L


def test_submit_poll_and_fetch_images(cluster: Cluster) -> None:
    p = 1 << 15
    job = cluster.submit(scene_name="furnace", settings={"max_passes": 24, "photons_per_pass": p, "seed": 2})
    assert job["status"] in ("queued", "running") and job["links"]["self"] == f"/v1/jobs/{job['id']}"
    done = cluster.wait(job["id"], finished)
    assert done["status"] == "completed", done
    assert done["passes"] == 24 and done["photons"] == 24 * p
    assert done["image_passes"] == 24  # a final job's image holds every pass it counts
    assert merged_passes(cluster.redis_client, job["id"]) == list(range(24))
    assert done["elapsed_seconds"] > 0 and done["photons_per_second"] > 0

    exr = cluster.http.get(job["links"]["image_exr"])
    assert exr.status_code == 200 and exr.headers["content-type"] == "image/x-exr"
    rgb = decode_image(exr.content, ".exr")
    assert rgb.shape == (64, 64, 3)
    assert abs(rgb.mean() / FURNACE_L - 1.0) < 0.02, rgb.mean()

    png = cluster.http.get(job["links"]["image_png"])
    assert png.status_code == 200 and png.content[:8] == b"\x89PNG\r\n\x1a\n"
    pixels = decode_image(png.content, ".png")
    assert pixels.shape == (64, 64, 3) and 0.2 < pixels.mean() < 0.9  # a lit, not saturated, image

    listed = cluster.http.get("/v1/jobs").json()
    assert job["id"] in [j["id"] for j in listed]


def test_images_read_while_rounds_fold_follow_the_passes(cluster: Cluster) -> None:
    """Clients polling a job's image and error map while fold rounds add to its state (in
    place when no reader holds it; readers wait for such a round, worker/store/overlay.py):
    every read answers, the passes each reader sees never go back, and the last image holds
    every pass. A round and readers that waited on each other for good would hang the job
    (`wait` fails it)."""
    passes = 40
    job = cluster.submit(scene_name="furnace", settings={"max_passes": passes, "photons_per_pass": 1 << 13, "seed": 3})
    stop, seen, bad = threading.Event(), [[], [], []], []

    def poll(i: int, kind: str) -> None:
        with httpx.Client(base_url=cluster.http.base_url, headers=cluster.http.headers, timeout=60) as client:
            while not stop.is_set():
                resp = client.get(f"/v1/jobs/{job['id']}/{kind}", params={"format": "png"})
                if resp.status_code == 200:
                    seen[i].append(int(resp.headers["X-Passes"]))
                elif resp.status_code != 409:  # 409: the error map before the first pass
                    bad.append((kind, resp.status_code, resp.text[:200]))

    readers = [threading.Thread(target=poll, args=(i, kind)) for i, kind in enumerate(("image", "image", "error"))]
    for reader in readers:
        reader.start()
    try:
        done = cluster.wait(job["id"], finished)
    finally:
        stop.set()
        for reader in readers:
            reader.join(60)
    assert done["status"] == "completed" and not bad, (done, bad)
    assert cluster.http.get(job["links"]["image_png"]).headers["X-Passes"] == str(passes)
    for reads in seen:
        assert reads and all(a <= b for a, b in pairwise(reads)), reads
    assert len(set(seen[0])) >= 2  # the reads spanned rounds


def test_unknown_job_is_404(cluster: Cluster) -> None:
    assert cluster.http.get("/v1/jobs/nope").status_code == 404
    assert cluster.http.get("/v1/jobs/nope/image").status_code == 404
    assert cluster.http.delete("/v1/jobs/nope").status_code == 404


def test_scenes_are_listed_and_served(cluster: Cluster) -> None:
    names = {s["name"] for s in cluster.http.get("/v1/scenes").json()}
    assert {"cornell-box", "cornell-caustics", "smallppm", "furnace", "point-plane"} <= names
    assert cluster.http.get("/v1/scenes/furnace").json()["lights"][0]["type"] == "point"
    assert cluster.http.get("/v1/scenes/no-such").status_code == 404


def test_cancel_stops_quickly_and_keeps_the_image(cluster: Cluster) -> None:
    p = 1 << 16
    job = cluster.submit(scene_name="cornell-box", settings={"max_seconds": 300, "photons_per_pass": p,
                                                             "resolution": [64, 64]})
    cluster.wait(job["id"], lambda j: j["passes"] >= 2)
    resp = cluster.http.delete(f"/v1/jobs/{job['id']}")
    assert resp.status_code == 202 and resp.json()["status"] in ("cancel-requested", "cancelled")
    done = cluster.wait(job["id"], finished, timeout=10)
    assert done["status"] == "cancelled"
    assert done["photons"] == done["passes"] * p
    assert sorted(set(merged_passes(cluster.redis_client, job["id"]))) == merged_passes(cluster.redis_client, job["id"])
    rgb = decode_image(cluster.http.get(job["links"]["image_exr"]).content, ".exr")
    assert rgb.mean() > 0.0  # the image of the merged passes is kept
    # a finished job is deleted, state and images with it
    assert cluster.http.delete(f"/v1/jobs/{job['id']}").status_code == 204
    assert cluster.http.get(f"/v1/jobs/{job['id']}").status_code == 404
    assert not cluster.redis_client.keys(f"pf:job:{job['id']}*")


def _bad(cluster: Cluster, body: dict, loc: list) -> None:
    resp = cluster.http.post("/v1/jobs", json=body)
    assert resp.status_code == 422, resp.text
    locs = [d["loc"] for d in resp.json()["detail"]]
    assert any(got[: len(loc)] == loc for got in locs), (loc, locs)


@pytest.mark.parametrize("body, loc", [
    ({"scene_name": "no-such-scene"}, ["body", "scene_name"]),
    ({}, ["body"]),
    ({"scene_name": "furnace", "scene": {}}, ["body"]),
    ({"scene_name": "furnace", "settings": {"alpha": 1.5}}, ["body", "settings", "alpha"]),
    ({"scene_name": "furnace", "settings": {"alpha": 0}}, ["body", "settings", "alpha"]),
    ({"scene_name": "furnace", "settings": {"method": "bdpt"}}, ["body", "settings", "method"]),
    ({"scene_name": "furnace", "settings": {"photons_per_pass": MAX_SERVICE_PHOTONS_PER_PASS + 1}},
     ["body", "settings", "photons_per_pass"]),
    ({"scene_name": "furnace", "settings": {"resolution": [4096, 4096]}}, ["body", "settings"]),
    ({"scene_name": "furnace", "settings": {"max_passes": 0}}, ["body", "settings", "max_passes"]),
    ({"scene_name": "furnace", "settings": {"seed": -1}}, ["body", "settings", "seed"]),
    ({"scene_name": "furnace", "settings": {"priority": "urgent"}}, ["body", "settings", "priority"]),
    ({"scene_name": "furnace", "settings": {"unknown": 1}}, ["body", "settings", "unknown"]),
])
def test_bad_settings_are_422_with_the_field(cluster: Cluster, body: dict, loc: list) -> None:
    _bad(cluster, body, loc)


def test_bad_inline_scenes_are_422_with_the_field(cluster: Cluster) -> None:
    scene = cluster.http.get("/v1/scenes/furnace").json()
    bad = {**scene, "shapes": [{**scene["shapes"][0], "radius": -1}]}
    _bad(cluster, {"scene": bad}, ["body", "scene", "shapes", 0, "radius"])
    bad = {**scene, "materials": {"wall": {"type": "glass", "ior": 9}}}
    _bad(cluster, {"scene": bad}, ["body", "scene", "materials", "wall", "ior"])
    bad = {**scene, "shapes": [{"type": "mesh", "file": "../../etc/passwd.obj", "material": "wall"}]}
    _bad(cluster, {"scene": bad}, ["body", "scene", "shapes", 0, "file"])
    bad = {**scene, "camera": {**scene["camera"], "resolution": [4000, 2200]}}
    _bad(cluster, {"scene": bad}, ["body", "scene", "camera"])
    resp = cluster.http.post("/v1/jobs", content=b"{not json", headers={"content-type": "application/json"})
    assert resp.status_code == 422


def test_oversized_body_is_413(cluster: Cluster) -> None:
    big = b'{"scene": {"x": "' + b"a" * (MAX_BODY_BYTES + 10) + b'"}}'
    resp = cluster.http.post("/v1/jobs", content=big, headers={"content-type": "application/json"})
    assert resp.status_code == 413


def test_image_format_is_checked(cluster: Cluster) -> None:
    job = cluster.submit(scene_name="furnace", settings={"max_passes": 1, "photons_per_pass": 1024})
    resp = cluster.http.get(f"/v1/jobs/{job['id']}/image", params={"format": "jpg"})
    assert resp.status_code == 422 and resp.json()["detail"][0]["loc"] == ["query", "format"]


def test_jobs_at_once_are_limited(cluster: Cluster) -> None:
    """Not a bad field (429, not 422): the same request succeeds once a job has ended."""
    ids = []
    request = {"scene_name": "furnace", "settings": {"max_seconds": 120, "photons_per_pass": 1024}}
    try:
        while len(ids) < MAX_ACTIVE_JOBS + 1:
            resp = cluster.http.post("/v1/jobs", json=request)
            if resp.status_code == 429:
                assert "at once" in resp.json()["detail"]
                break
            assert resp.status_code == 201
            ids.append(resp.json()["id"])
        assert len(ids) <= MAX_ACTIVE_JOBS
        first = ids.pop(0)
        cluster.http.delete(f"/v1/jobs/{first}")
        cluster.wait(first, finished, timeout=30)
        resp = cluster.http.post("/v1/jobs", json=request)
        assert resp.status_code == 201, resp.text
        ids.append(resp.json()["id"])
    finally:
        for job_id in ids:
            cluster.http.delete(f"/v1/jobs/{job_id}")
    for job_id in ids:
        cluster.wait(job_id, finished, timeout=30)


def test_bearer_token(tmp_path: Path) -> None:
    c = Cluster(tmp_path, workers=0, token="s3cret")
    try:
        c.http.headers.pop("Authorization")
        assert c.http.get("/healthz").status_code == 200
        # the page, its script and the API description carry no data and load without it (so
        # /docs can offer its Authorize button); data routes do not
        for path in ("/", "/static/viewer.js", "/docs", "/openapi.json"):
            assert c.http.get(path).status_code == 200, path
        for path in ("/v1/jobs", "/v1/scenes", "/v1/workers", "/metrics"):
            resp = c.http.get(path)
            assert resp.status_code == 401 and resp.headers["www-authenticate"] == "Bearer", path
        assert c.http.get("/v1/jobs", headers={"Authorization": "Bearer wrong"}).status_code == 401
        assert c.http.get("/v1/jobs", headers={"Authorization": "Bearer s3cret"}).status_code == 200
        assert c.http.post("/v1/jobs", json={"scene_name": "furnace"}).status_code == 401
    finally:
        c.close()
