"""Faults: a worker SIGKILLed mid-batch, the API killed and restarted, Redis killed and
restarted, the state nodes restarted while the reducer is down (the pending deltas lost); each
with one Redis and with the job state sharded over three more. And a state node that
stalls while a worker pushes its batch. Each job
must still finish, with every pass merged exactly once: the passes and photon totals add
up exactly, and the merged batches tile 0..max_passes-1. Each with every method
(cluster.METHODS: SPPM, the hybrid integrator vcm, and SPPM's adaptive sampler)."""

from __future__ import annotations

import signal
import time

import pytest

from api_tests.cluster import METHODS, Cluster
from api_tests.helpers import assert_exact
from worker.store import Batch, Jobs, Leases, keys

P = 1 << 16
PASSES = 40


@pytest.fixture(params=[0, 3], ids=["one-redis", "3-shards"])
def faulty(tmp_path, request) -> Cluster:  # a fresh cluster per fault
    """One Redis, or the job state over 3 more (tiles of 2048 pixels: 5 tiles a job)."""
    c = Cluster(tmp_path, workers=2, shards=request.param, env={"PHOTONFARM_TILE_PIXELS": "2048"})
    yield c
    c.close()


def _long_job(c: Cluster, method: str) -> dict:
    return c.submit(scene_name="cornell-box", settings={**METHODS[method], "max_passes": PASSES, "photons_per_pass": P,
                                                        "resolution": [96, 96], "seed": 9})


def _worker_holding_a_lease(c: Cluster, job_id: str, timeout: float = 30.0) -> int:
    """Index of a worker process that is running a batch of the job right now."""
    deadline = time.time() + timeout
    r = c.redis_client
    while time.time() < deadline:
        owners = {v.decode() for k, v in r.hgetall("pf:lease-owner").items() if k.decode().startswith(job_id)}
        for i, proc in enumerate(c.workers):
            if any(str(proc.pid) in owner for owner in owners):
                return i
        time.sleep(0.05)
    raise AssertionError("no worker took a batch")


EVERY_METHOD = pytest.mark.parametrize("method", list(METHODS))


@EVERY_METHOD
def test_worker_killed_mid_batch(faulty: Cluster, method: str) -> None:
    job = _long_job(faulty, method)
    faulty.wait(job["id"], lambda j: j["passes"] >= 2)
    victim = _worker_holding_a_lease(faulty, job["id"])
    faulty.workers[victim].send_signal(signal.SIGKILL)
    faulty.workers[victim].wait()
    passes_then = faulty.job(job["id"])["passes"]
    assert passes_then < PASSES, "the job finished before the kill: make it longer"
    assert_exact(faulty, job["id"], PASSES, P, timeout=180)


@EVERY_METHOD
def test_api_restart(faulty: Cluster, method: str) -> None:
    job = _long_job(faulty, method)
    faulty.wait(job["id"], lambda j: j["passes"] >= 2)
    faulty.kill_api()
    time.sleep(1.0)  # workers keep rendering and feeding the job without the API
    faulty.start_api()
    assert_exact(faulty, job["id"], PASSES, P, timeout=180)


@EVERY_METHOD
def test_redis_restart(faulty: Cluster, method: str) -> None:
    job = _long_job(faulty, method)
    faulty.wait(job["id"], lambda j: j["passes"] >= 4)
    before = faulty.job(job["id"])["passes"]
    for server in [faulty.redis, *faulty.shards[:1]]:  # the main Redis, and a state node
        faulty.restart_redis(server)
    after = faulty.wait(job["id"], lambda j: True)
    assert after["passes"] >= before  # nothing merged was lost (append-only file, fsync always)
    assert_exact(faulty, job["id"], PASSES, P, timeout=180)


@EVERY_METHOD
def test_deltas_lost_with_the_reducer_are_rendered_again(faulty: Cluster, method: str) -> None:
    """The reducer down (no folder holds the accepted batches in memory) and the state nodes
    restarted while batches wait to be folded: their deltas are gone (not in the nodes'
    append-only files); a round finds them missing, the batches are rendered again, and the
    job ends exact."""
    job = _long_job(faulty, method)
    faulty.wait(job["id"], lambda j: j["passes"] >= 2)
    for reducer in faulty.reducers:
        faulty.kill_reducer(reducer)
    jobs = Jobs(faulty.redis_client)
    deadline = time.time() + 60
    while (record := jobs.get(job["id"])).passes <= record.image_passes:  # accepted, not yet folded
        assert time.time() < deadline and record.passes < PASSES, "no batch waited for a fold"
        time.sleep(0.02)
    for server in faulty.shards or [faulty.redis]:  # every node that holds the job's state
        faulty.restart_redis(server)
    faulty.start_reducer()
    assert_exact(faulty, job["id"], PASSES, P, timeout=180)
    logs = "".join((faulty.data_dir / f"{name}.log").read_text(errors="replace") for name in ("reducers", "workers"))
    assert "deltas lost by a state node's restart" in logs


@EVERY_METHOD
def test_redis_down_while_workers_render(tmp_path, method: str) -> None:
    """Redis gone for longer than a pass while both workers hold a batch: their renewals
    fail, and RQ, filing each batch's failure on the dead Redis, quits its work loop. The
    worker processes start a new loop once Redis is back, and the job still finishes with
    every pass once."""
    c = Cluster(tmp_path, workers=2)
    try:
        job = _long_job(c, method)
        c.wait(job["id"], lambda j: j["passes"] >= 2)
        _worker_holding_a_lease(c, job["id"])
        c.redis.proc.send_signal(signal.SIGKILL)
        c.redis.proc.wait()
        time.sleep(3.0)
        c.redis.start(supervise=False)
        assert_exact(c, job["id"], PASSES, P, timeout=180)
        assert all(proc.poll() is None for proc in c.workers), "a worker process exited"
    finally:
        c.close()


def _between_passes(c: Cluster, job_id: str, timeout: float = 60.0) -> Batch:
    """A batch of the job whose worker, the job's only one, has rendered one or more of its
    passes and has one or more to go: it read the batch's inputs and reads nothing more from
    the state nodes until it pushes the batch's delta. (The worker's heartbeat names the
    batch it took and counts every pass it rendered: the job's passes before the batch, and
    the batch's.)"""
    leases, r = Leases(c.redis_client), c.redis_client
    deadline = time.time() + timeout
    while time.time() < deadline:
        for member, owner in r.hgetall(keys.LEASE_OWNER).items():
            batch = Batch.parse(member.decode())
            beat = leases.heartbeats().get(owner.decode(), {})
            if batch.job_id == job_id and beat.get("batch") == batch.id and \
                    0 < int(beat.get("passes", 0)) - batch.first < batch.n:
                return batch
        time.sleep(0.02)
    raise AssertionError("no batch was caught with a pass to go")


@EVERY_METHOD
def test_a_batch_pushing_to_a_stalled_state_node_keeps_its_lease(tmp_path, method: str) -> None:
    """The job's state node stalls (SIGSTOP: as a slow link or a long write would) for
    several leases while the worker renders a batch and then pushes it. The worker's
    heartbeat keeps the batch's lease through the push, so the reaper issues it to no one
    else (a lapsed lease during a push had another worker render it again, in vain: a 4K
    batch's half-GB push outlasted the tests' 4 s leases), and the job ends exact."""
    c = Cluster(tmp_path, workers=1, shards=1, env={"PHOTONFARM_LEASE_SECONDS": "1"})
    try:
        job = _long_job(c, method)
        _between_passes(c, job["id"])
        node = c.shards[0].proc
        node.send_signal(signal.SIGSTOP)
        try:
            time.sleep(8.0)  # the batch's last passes, then its push waits: 8 leases, 4 looks of the reaper
        finally:
            node.send_signal(signal.SIGCONT)
        assert_exact(c, job["id"], PASSES, P, timeout=180)
        reducer_log = (c.data_dir / "reducers.log").read_text()
        assert "re-issued lost batches" not in reducer_log
    finally:
        c.close()
