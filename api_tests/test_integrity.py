"""Service integrity where fault, fuzz and load testing broke it (issue 10): each test
fails on the code before the fix. Real Redis, real workers, real HTTP; where a job is
involved, exact pass and photon totals (every merged pass exactly once). The store-only
half is tests/test_store_integrity.py."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import httpx
import pytest
from rq import Worker

from api_tests.cluster import METHODS, Cluster
from api_tests.helpers import assert_exact
from service.models import MAX_ACTIVE_JOBS
from worker.scheduler import QUEUE_NAMES
from worker.store import Jobs

P = 1 << 12


def _small_job(c: Cluster, passes: int = 4, **settings: object) -> dict:
    return c.submit(scene_name="furnace", settings={"max_passes": passes, "photons_per_pass": P,
                                                     "resolution": [16, 16], **settings})


@pytest.mark.parametrize("method", list(METHODS))
def test_a_batch_dequeued_by_a_worker_that_died_is_reissued(tmp_path: Path, method: str) -> None:
    """A worker that dies after RQ moved a batch out of its queue and before starting it
    leaves the RQ job 'queued' in no queue (the state an RQ worker leaves between dequeue
    and start; made here by taking the job off the queue as such a worker does). The
    reaper must see that it is not waiting and re-issue it."""
    c = Cluster(tmp_path, workers=0)
    try:
        job = _small_job(c, passes=2, **METHODS[method])
        r = c.redis_client
        queue = f"rq:queue:{QUEUE_NAMES[1]}"
        taken = r.lpop(queue)  # the dying worker's dequeue
        assert taken is not None and r.llen(queue) == 0
        c.start_worker()
        assert_exact(c, job["id"], 2, P, timeout=90)
    finally:
        c.close()


def test_dead_workers_do_not_count_as_capacity(tmp_path: Path) -> None:
    c = Cluster(tmp_path, workers=2)
    try:
        jobs = Jobs(c.redis_client)
        deadline = time.time() + 30
        while jobs.leases.live_workers() < 2 and time.time() < deadline:
            time.sleep(0.2)
        assert jobs.leases.live_workers() == 2
        c.workers[0].kill()
        c.workers[0].wait()
        deadline = time.time() + 40  # ALIVE_SECONDS is 3 leases (12 s here), then a reap
        while time.time() < deadline and (jobs.leases.live_workers() != 1
                                          or Worker.count(connection=c.redis_client) != 1):
            time.sleep(0.5)
        assert jobs.leases.live_workers() == 1
        assert Worker.count(connection=c.redis_client) == 1  # its RQ registration is gone too
        alive = [w for w in c.http.get("/v1/workers").json() if w["alive"]]
        assert [w["pid"] for w in alive] == [c.workers[1].pid]
    finally:
        c.close()


def test_a_queued_job_cancels_at_once_and_renders_nothing(tmp_path: Path) -> None:
    c = Cluster(tmp_path, workers=0)
    try:
        job = _small_job(c, passes=50)
        resp = c.http.delete(f"/v1/jobs/{job['id']}")
        assert resp.status_code == 202 and resp.json()["status"] == "cancelled"  # nothing was rendering
        assert Jobs(c.redis_client).active_count() == 0  # the slot is free
        c.start_worker()
        time.sleep(6.0)  # the worker finds the queued batch and must not render it
        beats = Jobs(c.redis_client).leases.heartbeats()
        assert beats and all(int(b.get("passes", 0)) == 0 for b in beats.values()), beats
        assert c.job(job["id"])["passes"] == 0
    finally:
        c.close()


def test_concurrent_submits_respect_the_active_job_limit(tmp_path: Path) -> None:
    c = Cluster(tmp_path, workers=0)
    try:
        codes: list[int] = []
        gate = threading.Barrier(24)

        def post() -> None:
            with httpx.Client(base_url=str(c.http.base_url), timeout=60) as h:
                gate.wait()
                settings = {"max_seconds": 60, "photons_per_pass": P}
                codes.append(h.post("/v1/jobs", json={"scene_name": "furnace", "settings": settings}).status_code)

        threads = [threading.Thread(target=post) for _ in range(24)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        assert codes.count(201) == MAX_ACTIVE_JOBS and codes.count(429) == 24 - MAX_ACTIVE_JOBS, codes
        assert Jobs(c.redis_client).active_count() == MAX_ACTIVE_JOBS
    finally:
        c.close()


def test_a_pass_longer_than_the_lease_keeps_its_lease(tmp_path: Path) -> None:
    """Leases of 1 s, passes of several: the worker's heartbeat thread keeps the lease, so
    nothing is re-issued and no work is done twice."""
    c = Cluster(tmp_path, workers=1, env={"PHOTONFARM_LEASE_SECONDS": "1"})
    try:
        photons = 1 << 20
        job = c.submit(scene_name="cornell-caustics", settings={"max_passes": 2, "photons_per_pass": photons,
                                                                "resolution": [64, 64], "sampler": "uniform"})
        done = assert_exact(c, job["id"], 2, photons, timeout=300)
        record = Jobs(c.redis_client).get(job["id"])
        assert record.render_seconds / 2 > 1.0, "passes were not longer than the lease: the test proves nothing"
        log = (tmp_path / "reducers.log").read_text() + (tmp_path / "workers.log").read_text()
        assert "re-issued lost batches" not in log
        assert '"outcome": "duplicate"' not in log and "batch skipped" not in log
        assert done["passes"] == 2
    finally:
        c.close()


def test_finished_jobs_expire_and_can_be_deleted(tmp_path: Path) -> None:
    c = Cluster(tmp_path, workers=1, env={"PHOTONFARM_RETENTION_SECONDS": "3"})
    try:
        kept, deleted = _small_job(c, passes=2), _small_job(c, passes=2)
        for job in (kept, deleted):
            assert_exact(c, job["id"], 2, P)
        assert c.http.delete(f"/v1/jobs/{deleted['id']}").status_code == 204
        assert c.http.get(f"/v1/jobs/{deleted['id']}").status_code == 404
        assert not c.redis_client.keys(f"pf:job:{deleted['id']}*")
        r = c.redis_client
        # The scene has a key of its own: the record, read several times a batch, does not carry it.
        assert r.exists(f"pf:job:{kept['id']}:scene") and not r.hexists(f"pf:job:{kept['id']}", "scene")
        ttls = [r.ttl(k) for k in r.keys(f"pf:job:{kept['id']}*")]
        assert ttls and all(0 < t <= 3 for t in ttls), ttls  # every key of the job has its retention
        time.sleep(4.0)
        assert c.http.get(f"/v1/jobs/{kept['id']}").status_code == 404
        assert not r.keys(f"pf:job:{kept['id']}*")
        assert kept["id"] not in [j["id"] for j in c.http.get("/v1/jobs").json()]
    finally:
        c.close()


def test_jobs_are_listed_a_page_at_a_time(tmp_path: Path) -> None:
    c = Cluster(tmp_path, workers=0)
    try:
        ids = [_small_job(c, passes=1)["id"] for _ in range(5)]
        resp = c.http.get("/v1/jobs", params={"limit": 2, "offset": 1})
        assert resp.status_code == 200 and resp.headers["x-total-count"] == "5"
        assert [j["id"] for j in resp.json()] == ids[::-1][1:3]  # newest first
        assert c.http.get("/v1/jobs", params={"limit": 0}).status_code == 422
        assert c.http.get("/v1/jobs", params={"offset": 10}).json() == []  # past the last job: an empty page
        beyond = c.http.get("/v1/jobs", params={"offset": 10 ** 20})  # past Redis's 64-bit ranges: not a 500
        assert beyond.status_code == 422 and beyond.json()["detail"][0]["loc"] == ["query", "offset"]
    finally:
        c.close()


def test_a_full_job_store_answers_507_not_500(tmp_path: Path) -> None:
    """Redis runs with a memory cap and no eviction (a job's state is never dropped): once
    full it refuses writes, and the API says so. A cap below what an empty Redis uses makes
    it full from the start."""
    c = Cluster(tmp_path, workers=0, redis_maxmemory="100kb")
    try:
        resp = c.http.post("/v1/jobs", json={"scene_name": "furnace"})
        assert resp.status_code == 507 and "full" in resp.json()["detail"], resp.text
        assert c.http.get("/v1/jobs").status_code == 200  # reads still work
        assert c.http.get("/healthz").status_code == 200
    finally:
        c.close()
