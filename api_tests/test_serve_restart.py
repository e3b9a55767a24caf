"""The whole `photonfarm serve` process group (API, embedded Redis, local workers) killed
at several moments of a batch's life, then restarted on the same data directory: every job
finishes with exact totals (issue 10), with every method (cluster.METHODS)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import httpx
import pytest

from api_tests.cluster import METHODS
from service.redis_server import free_port

PASSES, P = 24, 1 << 14


class Serve:
    """`photonfarm serve` with an embedded Redis in `data`, in its own process group."""

    def __init__(self, data: Path) -> None:
        self.data, self.port = data, free_port()
        env = {**os.environ, "PHOTONFARM_LEASE_SECONDS": "4", "PYTHONUNBUFFERED": "1"}
        log = open(data.parent / "serve.log", "ab")  # the process keeps it
        self.proc = subprocess.Popen([sys.executable, "-m", "service.cli", "serve", "--port", str(self.port),
                                      "--workers", "2", "--data-dir", str(data)], env=env, stdout=log,
                                     stderr=subprocess.STDOUT, start_new_session=True)
        self.http = httpx.Client(base_url=f"http://127.0.0.1:{self.port}", timeout=30)
        deadline = time.time() + 90
        while time.time() < deadline:
            try:
                if self.http.get("/healthz").status_code == 200:
                    return
            except httpx.TransportError:
                pass
            time.sleep(0.2)
        raise RuntimeError("serve did not come up")

    def kill_group(self) -> None:
        os.killpg(self.proc.pid, signal.SIGKILL)
        self.proc.wait()
        deadline = time.time() + 10
        while time.time() < deadline and _group_alive(self.proc.pid):
            time.sleep(0.1)
        assert not _group_alive(self.proc.pid), "a child outlived the killed process group"

    def job(self, job_id: str) -> dict:
        return self.http.get(f"/v1/jobs/{job_id}").json()


def _group_alive(pgid: int) -> bool:
    return subprocess.run(["pgrep", "-g", str(pgid)], capture_output=True).returncode == 0


def _wait(s: Serve, job_id: str, until: Callable[[dict], bool], timeout: float) -> dict:
    deadline = time.time() + timeout
    while time.time() < deadline:
        try:
            job = s.job(job_id)
            if until(job):
                return job
        except httpx.TransportError:
            pass
        time.sleep(0.05)
    raise AssertionError(f"job {job_id} did not reach the condition: {s.job(job_id)}")


MOMENTS = {
    "queued": lambda job: True,  # at once: its first batches are still waiting in a queue
    "rendering": lambda job: job["workers_active"] > 0 and job["passes"] == 0,
    "merging": lambda job: job["passes"] >= 2,  # batches merge and new ones are issued
}


@pytest.mark.parametrize("method", list(METHODS))
@pytest.mark.parametrize("moment", list(MOMENTS))
def test_serve_killed_and_restarted_keeps_exact_totals(tmp_path: Path, moment: str, method: str) -> None:
    data = tmp_path / "data"
    s = Serve(data)
    try:
        job = s.http.post("/v1/jobs", json={"scene_name": "cornell-box", "settings": {**METHODS[method],
            "max_passes": PASSES, "photons_per_pass": P, "resolution": [48, 48], "seed": 4}}).json()
        _wait(s, job["id"], MOMENTS[moment], timeout=60)
    finally:
        s.kill_group()
    s = Serve(data)  # same data directory: the append-only file restores every job
    try:
        done = _wait(s, job["id"], lambda j: j["status"] not in ("queued", "running"), timeout=240)
        assert done["status"] == "completed", done
        assert done["passes"] == PASSES and done["photons"] == PASSES * P, done
    finally:
        s.kill_group()
