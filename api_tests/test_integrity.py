"""Service integrity where fault, fuzz and load testing broke it (issue 10): each test
fails on the code before the fix. Real Redis, real workers, real HTTP; where a job is
involved, exact pass and photon totals (every merged pass exactly once)."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import httpx
import pytest
import redis
from rq import Worker

from api_tests.cluster import METHODS, Cluster, finished, merged_passes
from service.models import MAX_ACTIVE_JOBS
from worker.scene import bundled_scene_path, inline_meshes, load_scene_file
from worker.scheduler import QUEUE_NAMES
from worker.settings import Settings
from worker.store import Batch, Jobs, Leases, Status, keys
from worker.store.policy import DELIVERY_SECONDS

P = 1 << 12


def _small_job(c: Cluster, passes: int = 4, **settings: object) -> dict:
    return c.submit(scene_name="furnace", settings={"max_passes": passes, "photons_per_pass": P,
                                                     "resolution": [16, 16], **settings})


def _assert_exact(c: Cluster, job_id: str, passes: int, photons: int = P, timeout: float = 120.0) -> dict:
    done = c.wait(job_id, finished, timeout=timeout)
    assert done["status"] == "completed", done
    assert done["passes"] == passes and done["photons"] == passes * photons, done
    assert merged_passes(c.redis_client, job_id) == list(range(passes))
    return done


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
        _assert_exact(c, job["id"], 2, timeout=90)
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
        while time.time() < deadline and (jobs.leases.live_workers() != 1 or Worker.count(connection=c.redis_client) != 1):
            time.sleep(0.5)
        assert jobs.leases.live_workers() == 1
        assert Worker.count(connection=c.redis_client) == 1  # its RQ registration is gone too
        alive = [w for w in c.http.get("/v1/workers").json() if w["alive"]]
        assert [w["pid"] for w in alive] == [c.workers[1].pid]
    finally:
        c.close()


def test_a_cancel_between_a_merges_read_and_write_is_kept(redis_url: str) -> None:
    """The cancel lands while a merge holds its read record (white box: the acceptance's
    read triggers it). The merge must retry and see it, not write 'running' back."""
    conn = redis.Redis.from_url(redis_url)
    parsed, base = load_scene_file(bundled_scene_path("furnace"))
    settings = Settings(max_passes=100, photons_per_pass=P, resolution=(8, 8))
    jobs = Jobs(conn)
    job_id = jobs.create(inline_meshes(parsed, base), settings, 8, 8, "furnace")
    batch = jobs.allocate(job_id)
    assert jobs.start(batch, "w1")  # a worker holds it: the cancel cannot just drop it
    record = jobs.get(job_id)
    jobs.init_setup(record, {"R0": [0.1] * 64})
    integrator = record.integrator
    delta_sums = {name: integrator.sums.zeros(64, name) for name in integrator.sums.names}
    from worker.integrators.base import Delta

    class CancelledMidMerge(Jobs):
        fired = False

        def _read(self, pipe, job):  # noqa: ANN001, ANN202 - the acceptance's read, before its write
            record = super()._read(pipe, job)
            if not CancelledMidMerge.fired:
                CancelledMidMerge.fired = True
                Jobs(conn).cancel(job)
            return record

    outcome = CancelledMidMerge(conn).merge(batch, Delta(batch.first, batch.n, batch.n * P, delta_sums), 0.1)
    assert CancelledMidMerge.fired and outcome == "merged"
    done = jobs.get(job_id)
    assert done.status == Status.CANCELLED, done.status
    assert done.passes == batch.n and done.emitted == batch.n * P


def test_a_cancel_as_a_worker_takes_a_batch_keeps_the_slot_until_the_batch_ends(redis_url: str) -> None:
    """The cancel lands while a worker takes a batch's lease (white box: the lease's take
    triggers it). Either the worker does not start the batch and the job is cancelled, or
    it renders and the job holds its slot (cancel-requested) until the batch is dropped:
    never a cancelled job, its slot free, with a batch rendering."""
    conn = redis.Redis.from_url(redis_url)
    parsed, base = load_scene_file(bundled_scene_path("furnace"))
    jobs = Jobs(conn)
    job_id = jobs.create(inline_meshes(parsed, base), Settings(max_passes=100, photons_per_pass=P, resolution=(8, 8)),
                         8, 8, "furnace", max_active=1)
    batch = jobs.allocate(job_id)

    class CancelledAtTake(Leases):
        fired = False

        def take(self, *args, **kwargs):  # noqa: ANN002, ANN003, ANN202 - the cancel, then the take
            if not CancelledAtTake.fired:
                CancelledAtTake.fired = True
                assert Jobs(conn).cancel(job_id) == Status.CANCELLED  # nothing was rendering yet
            return super().take(*args, **kwargs)

    jobs.leases = CancelledAtTake(conn)
    started = jobs.start(batch, "w1")
    assert CancelledAtTake.fired
    status = jobs.status(job_id)
    if started:
        assert status == Status.CANCEL_REQUESTED and jobs.active_count() == 1, status
        assert jobs.renew(batch, "w1") != Status.RUNNING  # the worker stops after its pass
        jobs.drop(batch)
        status = jobs.status(job_id)
    assert status == Status.CANCELLED and jobs.active_count() == 0, status
    assert conn.zscore(keys.LEASES, batch.member) is None and not conn.hexists(keys.LEASE_OWNER, batch.member)


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
                codes.append(h.post("/v1/jobs", json={"scene_name": "furnace",
                                                      "settings": {"max_seconds": 60, "photons_per_pass": P}}).status_code)

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
                                                                "resolution": [64, 64]})
        done = _assert_exact(c, job["id"], 2, photons=photons, timeout=300)
        record = Jobs(c.redis_client).get(job["id"])
        assert record.render_seconds / 2 > 1.0, "passes were not longer than the lease: the test proves nothing"
        log = (tmp_path / "api.log").read_text() + (tmp_path / "workers.log").read_text()
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
            _assert_exact(c, job["id"], 2)
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


def test_batches_of_an_unknown_job_are_not_rendered(redis_url: str) -> None:
    """A batch whose job was deleted while it waited is skipped, not rendered."""
    jobs = Jobs(redis.Redis.from_url(redis_url))
    job_id = jobs.create({}, Settings(max_passes=2), 8, 8, None)
    batch = jobs.allocate(job_id)
    jobs.delete(job_id)
    assert not jobs.start(batch, "w1")
    assert not jobs.r.keys(keys.job(job_id) + "*")
    assert isinstance(batch, Batch)


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


def test_batches_allocated_together_are_due_one_refresh_after_another(redis_url: str) -> None:
    """Each allocation records when its batch is due; the next one, told, ends at most
    DELIVERY_SECONDS after it (policy.batch_passes), not together with it. A merged or
    dropped batch is no longer due."""
    conn = redis.Redis.from_url(redis_url)
    parsed, base = load_scene_file(bundled_scene_path("furnace"))
    jobs = Jobs(conn)
    job_id = jobs.create(inline_meshes(parsed, base), Settings(photons_per_pass=P, resolution=(8, 8)), 8, 8,
                         "furnace")
    conn.hset(keys.job(job_id), mapping={"merge_seconds": 1.0, "merges": 1, "fold_rounds": "[[1, 1.0]]"})
    first = jobs.allocate(job_id, pass_seconds=1.0, workers=2)
    second = jobs.allocate(job_id, pass_seconds=1.0, workers=2)
    assert first is not None and second is not None
    due = dict(conn.zrange(keys.due(job_id), 0, -1, withscores=True))
    at_first, at_second = due[first.id.encode()], due[second.id.encode()]
    assert at_first - time.time() <= DELIVERY_SECONDS
    assert 0.0 < at_second - at_first <= DELIVERY_SECONDS + 0.5
    assert second.n > first.n  # longer: its delivery falls between the first worker's
    jobs.drop(first)
    assert conn.zrange(keys.due(job_id), 0, -1) == [second.id.encode()]
