"""Operations: Prometheus metrics, the worker list with heartbeats, structured logs, and
`photonfarm submit` as a client of the HTTP API."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from api_tests.cluster import Cluster, finished
from service.app import METRICS_SECONDS
from tests.analytic import FURNACE_L
from worker.image_io import read_image
from worker.scheduler import QUEUE_NAMES

PHOTONFARM = [sys.executable, "-m", "service.cli"]


def _metric(text: str, name: str, labels: str = "") -> float:
    for line in text.splitlines():
        if line.startswith(f"{name}{labels} ") or (not labels and line.startswith(f"{name} ")):
            return float(line.split()[-1])
    raise AssertionError(f"{name}{labels} not in metrics:\n{text}")


def test_metrics_workers_and_logs(cluster: Cluster) -> None:
    job = cluster.submit(scene_name="furnace", settings={"max_passes": 6, "photons_per_pass": 1 << 13})
    cluster.wait(job["id"], finished)
    text = cluster.http.get("/metrics").text
    assert _metric(text, "photonfarm_jobs", '{status="completed"}') >= 1
    assert _metric(text, "photonfarm_batches_merged_total") >= 1
    assert _metric(text, "photonfarm_passes_merged_total") >= 6
    assert _metric(text, "photonfarm_merge_latency_seconds_count") >= 1
    assert _metric(text, "photonfarm_merge_latency_seconds_sum") > 0
    assert 0 <= _metric(text, "photonfarm_image_age_seconds") <= 60
    assert _metric(text, "photonfarm_queue_depth", '{queue="photonfarm-normal"}') == 0  # nothing left waiting
    assert _metric(text, "photonfarm_workers_alive") == len(cluster.workers)

    workers = cluster.http.get("/v1/workers").json()
    assert {w["pid"] for w in workers} == {p.pid for p in cluster.workers}
    assert all(w["alive"] and w["last_seen_seconds_ago"] < 60 for w in workers)
    assert sum(w["passes"] for w in workers) >= 6  # heartbeats after every pass

    lines = [json.loads(line) for line in (cluster.data_dir / "workers.log").read_text().splitlines()
             if line.startswith("{")]
    done = [entry for entry in lines if entry.get("job") == job["id"] and entry["msg"] == "batch done"]
    assert done and all({"batch", "worker", "outcome", "seconds", "ts", "level"} <= set(e) for e in done)
    assert {e["outcome"] for e in done} <= {"merged", "duplicate", "inactive"}


def test_queue_depth_counts_waiting_batches(tmp_path: Path) -> None:
    """With no worker, a submitted job's batch waits in its priority's queue (one batch:
    scheduler.target_inflight with no live worker), none in the others; a worker then
    takes it and the job's later batches, and the queue is empty once the job is done."""
    c = Cluster(tmp_path, workers=0)
    try:
        job = c.submit(scene_name="furnace", settings={"max_passes": 4, "photons_per_pass": 1 << 13})
        text = c.http.get("/metrics").text
        for name in QUEUE_NAMES:
            assert _metric(text, "photonfarm_queue_depth", f'{{queue="{name}"}}') == (name == "photonfarm-normal"), name
        c.start_worker()
        assert c.wait(job["id"], finished)["status"] == "completed"
        time.sleep(1.1 * METRICS_SECONDS)  # past the scrape cached before the job ended
        assert _metric(c.http.get("/metrics").text, "photonfarm_queue_depth", '{queue="photonfarm-normal"}') == 0
    finally:
        c.close()


def test_submit_watch_writes_the_final_image(cluster: Cluster, tmp_path: Path) -> None:
    out = tmp_path / "furnace.exr"
    proc = subprocess.run([*PHOTONFARM, "submit", "furnace", "--url", str(cluster.http.base_url), "--max-passes", "8",
                           "--photons-per-pass", "16384", "--watch", "--poll", "0.2", "--out", str(out)],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert "completed: 8 passes" in proc.stdout and "\r" not in proc.stderr  # no progress redraws in a log
    assert abs(read_image(out).mean() / FURNACE_L - 1.0) < 0.03


def test_submit_errors_are_one_clear_line(cluster: Cluster, tmp_path: Path) -> None:
    bad = subprocess.run([*PHOTONFARM, "submit", "no-such-scene", "--url", str(cluster.http.base_url)],
                         capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "scene_name" in bad.stderr and "Traceback" not in bad.stderr
    down = subprocess.run([*PHOTONFARM, "submit", "furnace", "--url", "http://127.0.0.1:9"],
                          capture_output=True, text=True, timeout=60)
    assert down.returncode == 2 and "cannot reach" in down.stderr and "Traceback" not in down.stderr
    scene = json.loads(cluster.http.get("/v1/scenes/furnace").text)
    scene["shapes"][0]["radius"] = -1
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(scene))
    inline = subprocess.run([*PHOTONFARM, "submit", str(path), "--url", str(cluster.http.base_url)],
                            capture_output=True, text=True, timeout=60)
    assert inline.returncode == 2 and "scene.shapes.0.radius" in inline.stderr
    text = tmp_path / "scene.txt"
    text.write_text(json.dumps(scene))
    other = subprocess.run([*PHOTONFARM, "submit", str(text), "--url", str(cluster.http.base_url)],
                           capture_output=True, text=True, timeout=60)
    assert other.returncode == 2 and ".json" in other.stderr and "scene_name" not in other.stderr, other.stderr


def test_submit_watch_checks_its_output_before_submitting(cluster: Cluster, tmp_path: Path) -> None:
    """An image that cannot be written is said before the job runs, not after it ends."""
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    before = cluster.http.get("/v1/jobs").headers["x-total-count"]
    proc = subprocess.run([*PHOTONFARM, "submit", "furnace", "--url", str(cluster.http.base_url), "--max-passes", "2",
                           "--watch", "--out", str(blocker / "x.png")], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and "cannot write" in proc.stderr and "Traceback" not in proc.stderr, proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1
    assert cluster.http.get("/v1/jobs").headers["x-total-count"] == before  # nothing was submitted
    wrong = subprocess.run([*PHOTONFARM, "submit", "furnace", "--url", str(cluster.http.base_url),
                            "--out", str(tmp_path / "x.bmp")], capture_output=True, text=True, timeout=60)
    assert wrong.returncode == 2 and ".exr or .png" in wrong.stderr


def test_image_stays_finite(cluster: Cluster) -> None:
    job = cluster.submit(scene_name="furnace", settings={"max_passes": 2, "photons_per_pass": 4096})
    cluster.wait(job["id"], finished)
    assert np.isfinite(cluster.job(job["id"])["error_estimate"]["error"])
