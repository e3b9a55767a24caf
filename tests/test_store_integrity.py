"""Store integrity where fault, fuzz and load testing broke it (issue 10; the HTTP half is
api_tests/test_integrity.py): a cancel racing a merge, a batch of a deleted job, and the
due times of batches allocated together. Real Redis, the store called directly."""

from __future__ import annotations

import time

import redis

from worker.config import config
from worker.integrators.base import Delta
from worker.scene import bundled_scene_path, inline_meshes, load_scene_file
from worker.settings import Settings
from worker.store import Batch, Jobs, Leases, Status, keys

P = 1 << 12


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

    class CancelledMidMerge(Jobs):
        fired = False

        def _read(self, pipe, job):  # the acceptance's read, before its write
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


def test_batches_of_an_unknown_job_are_not_rendered(redis_url: str) -> None:
    """A batch whose job was deleted while it waited is skipped, not rendered."""
    jobs = Jobs(redis.Redis.from_url(redis_url))
    job_id = jobs.create({}, Settings(max_passes=2), 8, 8, None)
    batch = jobs.allocate(job_id)
    jobs.delete(job_id)
    assert not jobs.start(batch, "w1")
    assert not jobs.r.keys(keys.job(job_id) + "*")
    assert isinstance(batch, Batch)


def test_batches_allocated_together_are_due_one_refresh_after_another(redis_url: str) -> None:
    """Each allocation records when its batch is due; the next one, told, ends at most
    delivery_seconds after it (policy.batch_passes), not together with it. A merged or
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
    assert at_first - time.time() <= config().delivery_seconds
    assert 0.0 < at_second - at_first <= config().delivery_seconds + 0.5
    assert second.n > first.n  # longer: its delivery falls between the first worker's
    jobs.drop(first)
    assert conn.zrange(keys.due(job_id), 0, -1) == [second.id.encode()]


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

        def take(self, *args, **kwargs):  # the cancel, then the take
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
