"""The Redis key layout, in one place (every key under `pf:`).

    pf:jobs                        zset    job id -> creation time
    pf:active                      set     ids of jobs holding an active slot (queued, running, cancelling)
    pf:job:{id}                    hash    the job record (worker/store/record.py)
    pf:job:{id}:scene              string  the job's scene, JSON (read once per engine; the record is read often)
    pf:job:{id}:merged             set     batch ids accepted (counted in the record, exactly once)
    pf:job:{id}:tofold             hash    accepted batch id -> JSON {n, e, c}: passes, photons, counters not yet in the
                                           tiles' state (a checkpoint adds them to the record: folded_passes,
                                           folded_emitted, counter:NAME; worker/store/overlay.py)
    pf:job:{id}:lost               set     accepted batch ids whose delta a state node's restart lost on a tile that
                                           had not folded it (deltas stay out of the append-only file): each is
                                           rendered again under its id and refills those tiles (worker/store/record.py)
    pf:job:{id}:fold-lock          string  the fold lease: one folder per round at a time (worker/store/fold_lease.py)
    pf:job:{id}:reducer            string  the one reducer that owns the job, its lease (worker/reducer.py)
    pf:job:{id}:image              hash    the last fold round's image and error (worker/store/published.py)
    pf:job:{id}:history            list    JSON {passes, photons, seconds, error} after each fold round
    pf:job:{id}:inflight           set     batch ids issued and not yet merged or dropped
    pf:leases                      zset    batch member "job/first/n" -> deadline
    pf:lease-owner                 hash    batch member -> worker name
    pf:batch-rq                    hash    batch member -> id of the RQ job that carries it
    pf:fold-news                   list    ids of jobs whose ending batch was just accepted: the reducers wait
                                           on it between their looks (at most FOLD_NEWS_KEPT)
    pf:reaper                      string  the reaper lease: one reducer re-issues lost batches at a time
    pf:worker:{name}               hash    heartbeat: job, batch, passes, last_seen (expires)
    pf:workers                     zset    worker name -> last heartbeat (live workers: recent scores)

On the state nodes (worker/store/tiles.py: tile k of a job on node k mod nodes):

    pf:job:{id}:t{k}:state         hash    the folded state of tile k: state array name -> float64 bytes (absent: zero)
    pf:job:{id}:t{k}:inputs        string  what a batch reads for tile k (e.g. radius, bias; float32)
    pf:job:{id}:t{k}:pending       hash    batch id -> the batch's delta for tile k, pushed and not yet folded (kept
                                           out of the append-only file: a restart may lose it, pf:job:{id}:lost)
    pf:job:{id}:t{k}:folded        set     batch ids folded into tile k (exactly once per tile)
    pf:job:{id}:t{k}:meta          hash    version (bumped by every fold of the tile; folds WATCH it)
"""

from __future__ import annotations

JOBS = "pf:jobs"
ACTIVE = "pf:active"
WORKER_SEEN = "pf:workers"
LEASES = "pf:leases"
LEASE_OWNER = "pf:lease-owner"
BATCH_RQ = "pf:batch-rq"
FOLD_NEWS = "pf:fold-news"
FOLD_NEWS_KEPT = 64  # entries: with no reducer to take them, the list stays this short
REAPER = "pf:reaper"


def job(job_id: str) -> str:
    return f"pf:job:{job_id}"


def scene(job_id: str) -> str:
    return f"pf:job:{job_id}:scene"


def tofold(job_id: str) -> str:
    return f"pf:job:{job_id}:tofold"


def fold_lock(job_id: str) -> str:
    return f"pf:job:{job_id}:fold-lock"


def reducer(job_id: str) -> str:
    return f"pf:job:{job_id}:reducer"


def image(job_id: str) -> str:
    return f"pf:job:{job_id}:image"


TILE_PARTS = ("state", "inputs", "pending", "folded", "meta")


def tile(job_id: str, k: int, part: str) -> str:
    return f"pf:job:{job_id}:t{k}:{part}"


def merged(job_id: str) -> str:
    return f"pf:job:{job_id}:merged"


def lost(job_id: str) -> str:
    return f"pf:job:{job_id}:lost"


def history(job_id: str) -> str:
    return f"pf:job:{job_id}:history"


def inflight(job_id: str) -> str:
    return f"pf:job:{job_id}:inflight"


def due(job_id: str) -> str:
    """Sorted set: in-flight batch id -> when it is expected to be delivered (policy.batch_passes)."""
    return f"pf:job:{job_id}:due"


def job_keys(job_id: str) -> list[str]:
    """Every key of one job on the main Redis (its tiles' keys: `tile_keys`)."""
    return [job(job_id), scene(job_id), merged(job_id), tofold(job_id), lost(job_id), fold_lock(job_id),
            reducer(job_id), image(job_id), history(job_id), inflight(job_id), due(job_id)]


def tile_keys(job_id: str, k: int) -> list[str]:
    return [tile(job_id, k, part) for part in TILE_PARTS]


def worker(name: str) -> str:
    return f"pf:worker:{name}"

