"""The Redis key layout, in one place (every key under `pf:`).

    pf:jobs                        zset    job id -> creation time
    pf:active                      set     ids of jobs holding an active slot (queued, running, cancelling)
    pf:job:{id}                    hash    the job record (worker/store/record.py)
    pf:job:{id}:{name}             string  a float64 per-pixel array of the job state
    pf:job:{id}:version            int     bumped by every merge; merges WATCH it
    pf:job:{id}:merge-lock         string  serialises one job's merges (a redis-py lock)
    pf:job:{id}:merged             set     batch ids already merged (exactly once)
    pf:job:{id}:history            list    JSON {passes, photons, seconds, error} after each merge
    pf:job:{id}:inflight           set     batch ids issued and not yet merged or dropped
    pf:leases                      zset    batch member "job/first/n" -> deadline
    pf:lease-owner                 hash    batch member -> worker name
    pf:batch-rq                    hash    batch member -> id of the RQ job that carries it
    pf:worker:{name}               hash    heartbeat: job, batch, passes, last_seen (expires)
    pf:workers                     zset    worker name -> last heartbeat (live workers: recent scores)
"""

from __future__ import annotations

JOBS = "pf:jobs"
ACTIVE = "pf:active"
WORKER_SEEN = "pf:workers"
LEASES = "pf:leases"
LEASE_OWNER = "pf:lease-owner"
BATCH_RQ = "pf:batch-rq"


def job(job_id: str) -> str:
    return f"pf:job:{job_id}"


def array(job_id: str, name: str) -> str:
    return f"pf:job:{job_id}:{name}"


def version(job_id: str) -> str:
    return f"pf:job:{job_id}:version"


def merge_lock(job_id: str) -> str:
    return f"pf:job:{job_id}:merge-lock"


def merged(job_id: str) -> str:
    return f"pf:job:{job_id}:merged"


def history(job_id: str) -> str:
    return f"pf:job:{job_id}:history"


def inflight(job_id: str) -> str:
    return f"pf:job:{job_id}:inflight"


def job_keys(job_id: str, arrays: tuple[str, ...]) -> list[str]:
    """Every key of one job, given the names of its state arrays."""
    return [job(job_id), version(job_id), merge_lock(job_id), merged(job_id), history(job_id), inflight(job_id),
            *(array(job_id, name) for name in arrays)]


def worker(name: str) -> str:
    return f"pf:worker:{name}"

