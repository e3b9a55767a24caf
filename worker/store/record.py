"""The job record in Redis: creation, status transitions, batch allocation, and the
exactly-once acceptance of a batch whose delta was pushed to the job's tiles.

A batch's seeds come from (job seed, pass index), so a re-issued batch recomputes the same
passes, and the merged set makes sure they count once. A batch merges in two steps: its
worker pushes the delta to every tile's pending hash (worker/store/state.py), then one
MULTI/EXEC under WATCH of the record accepts it: counters, the merged set, the to-fold
hash, the lease released. A worker that dies before EXEC leaves at most pending entries
that the re-issued batch overwrites; a cancel landing between the acceptance's read and
write makes it retry and see it. Folding is separate (`fold`): only accepted batches are
folded, each into each tile once (rounds between checkpoints fold in the folder's memory,
worker/store/overlay.py). A job moves to a final status only once everything accepted is
folded and checkpointed, so its final image holds every pass it counts.

A delta is not in the state nodes' append-only files (worker/store/state.py), so a node's
restart can lose one of an accepted batch. The round that finds it marks the batch lost
and issues it again (`refill`): same id, same passes and seeds, rendered at the radii of
the moment. Its push refills the tiles that lack it (those that folded it before keep
theirs), and its acceptance only takes it out of the lost set: it counts once, as before.
Until then rounds fold the other batches and the job does not end, unless it is cancelled:
then its lost batches are taken back (`_give_up`).

Active jobs are a set (`pf:active`) changed in the same transaction as the status: a job
is created only if the set is below the limit (checked and added atomically), and every
move to a final status removes it and gives all the job's keys their retention time.
"""

from __future__ import annotations

import json
import logging
import time
import uuid
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import Any, cast

import numpy as np
import redis

from worker.config import config
from worker.integrators import Integrator, integrator_for
from worker.integrators.base import Delta, State
from worker.settings import Settings
from worker.store import keys, policy
from worker.store.connection import Fields, text, text_hash
from worker.store.leases import Batch, Leases
from worker.store.overlay import OVERLAYS
from worker.store.policy import Status
from worker.store.published import Images, Published
from worker.store.state import Folded, Snapshot, TiledState
from worker.store.tiles import Tiling

log = logging.getLogger("photonfarm.store")
COUNTER = "counter:"  # prefix of the job hash's fields that hold State.counters
# A job's notes (what its scene holds that was accepted but ignored) are kept in its record,
# which every poll of the job reads: bounded, whatever the scene holds (docs/limits.md).
MAX_JOB_NOTES = 32  # distinct notes kept; the rest are counted in a last line
MAX_NOTE_CHARS = 512  # one note: room for a file name of 255 characters and the rest of its line
# A field of a hash that exists (a deleted job's record is not brought back).
SET_IF_EXISTS = """
if redis.call('exists', KEYS[1]) == 1 then redis.call('hset', KEYS[1], ARGV[1], ARGV[2]) end
"""


def _scored(reply: object) -> list[tuple[bytes, float]]:
    """A ZRANGE ... WITHSCORES reply: (member, score) pairs (redis-py types it loosely)."""
    return cast("list[tuple[bytes, float]]", reply)


def bounded_notes(notes: Iterable[str]) -> tuple[str, ...]:
    """The notes as a record keeps them: the repeats dropped (first seen first), at most
    MAX_JOB_NOTES of them, each cut to MAX_NOTE_CHARS, and then "... and N more" counting
    the distinct notes left out."""
    distinct = list(dict.fromkeys(notes))
    kept = tuple(note if len(note) <= MAX_NOTE_CHARS else note[:MAX_NOTE_CHARS - 3] + "..."
                 for note in distinct[:MAX_JOB_NOTES])
    left_out = len(distinct) - len(kept)
    return (*kept, f"... and {left_out} more") if left_out else kept


class JobLimitReached(Exception):
    """The service holds as many active jobs as it allows."""


@dataclass(frozen=True)
class JobRecord:
    """A job's record (the hash `pf:job:{id}`), typed."""

    id: str
    status: Status
    settings: Settings
    scene_name: str | None
    width: int
    height: int
    created: float
    started: float | None
    finished: float | None
    passes: int  # accepted (merged)
    emitted: int  # photon paths of the accepted passes
    folded_passes: int  # in the state the tiles hold (the last checkpoint)
    folded_emitted: int
    image_passes: int  # in the image after the last fold round (checkpoint or overlay, worker/store/overlay.py)
    waiting_since: float  # accepted passes beyond the image have waited since (fold_if_stale)
    folded_at: float
    fold_rounds: tuple[policy.Round, ...]  # the recent rounds (policy.round_seconds)
    round_cost: float  # the last round's whole length, its checkpoint writes included (0 before any)
    setup: bool  # the tiles hold the setup arrays (e.g. R0)
    stopping: bool  # a move to a final status is under way: no new batches
    ending: Status | None  # the final status an accepted batch decided (Jobs.end_if_decided)
    shards: int  # state nodes the tiles are spread over
    tile_pixels: int
    next_pass: int  # first pass index not yet allocated
    pass_seconds: float  # smoothed render seconds per pass
    render_seconds: float
    render_cpu_seconds: float  # CPU time of the workers' processes while rendering (all their threads)
    longest_batch_seconds: float  # a batch's wall time from its lease to its push (engine build included)
    merges: int
    merge_seconds: float
    merge_cpu_seconds: float  # CPU time of the workers' processes while pushing and accepting
    failure: str | None
    counters: dict[str, int]  # the integrator's summed scalars (Delta.counters), hash fields "counter:NAME"
    notes: tuple[str, ...]  # what the scene holds that was accepted but ignored (bounded_notes), set at creation

    @classmethod
    def parse(cls, job_id: str, h: Mapping[bytes, bytes] | Mapping[bytes | str, bytes | str]) -> JobRecord:
        f = text_hash(h)

        def when(name: str) -> float | None:
            return float(f[name]) if f.get(name) else None

        return cls(id=job_id, status=Status(f["status"]), settings=Settings.model_validate_json(f["settings"]),
                   scene_name=f["scene_name"] or None, width=int(f["width"]), height=int(f["height"]),
                   created=float(f["created"]), started=when("started"), finished=when("finished"),
                   passes=int(f["passes"]), emitted=int(f["emitted"]),
                   folded_passes=int(f.get("folded_passes", 0)), folded_emitted=int(f.get("folded_emitted", 0)),
                   image_passes=int(f.get("image_passes", f.get("folded_passes", 0))),
                   waiting_since=float(f.get("waiting_since", 0.0)),
                   folded_at=float(f.get("folded_at", 0.0)),
                   fold_rounds=tuple(policy.Round(int(r[0]), float(r[1]), bool(r[2:] and r[2]))
                                     for r in json.loads(f.get("fold_rounds", "[]"))),
                   round_cost=float(f.get("round_cost", 0.0)),
                   setup=f.get("setup") == "1",
                   stopping=f.get("stopping") == "1", ending=Status(f["ending"]) if f.get("ending") else None,
                   shards=int(f.get("shards", 1)), tile_pixels=int(f.get("tile_pixels", config().tile_pixels)),
                   next_pass=int(f["next_pass"]),
                   pass_seconds=float(f["pass_seconds"]), render_seconds=float(f.get("render_seconds", 0.0)),
                   render_cpu_seconds=float(f.get("render_cpu_seconds", 0.0)),
                   longest_batch_seconds=float(f.get("longest_batch_seconds", 0.0)),
                   merges=int(f.get("merges", 0)), merge_seconds=float(f.get("merge_seconds", 0.0)),
                   merge_cpu_seconds=float(f.get("merge_cpu_seconds", 0.0)),
                   failure=f.get("error") or None,
                   counters={k[len(COUNTER):]: int(v) for k, v in f.items() if k.startswith(COUNTER)},
                   notes=tuple(json.loads(f.get("notes", "[]"))))

    @property
    def fold_seconds(self) -> float:
        """The last fold round's length to its image (0 before the first)."""
        return self.fold_rounds[-1].seconds if self.fold_rounds else 0.0

    @property
    def fold_cost(self) -> float:
        """What the last fold round cost the job: its whole length, the checkpoint writes
        after its image included; what the cost rules count (policy.batch_passes,
        fold_interval)."""
        return max(self.round_cost, self.fold_seconds)

    @property
    def n_pixels(self) -> int:
        return self.width * self.height

    @property
    def integrator(self) -> Integrator:
        return integrator_for(self.settings)

    def elapsed_seconds(self, now: float | None = None) -> float:
        if self.started is None:
            return 0.0
        end = self.finished or (time.time() if now is None else now)
        return max(0.0, end - self.started)

    @property
    def photons_per_second(self) -> float:
        elapsed = self.elapsed_seconds()
        return self.emitted / elapsed if elapsed > 0 else 0.0

    @property
    def mean_merge_seconds(self) -> float:
        return self.merge_seconds / self.merges if self.merges else 0.0


class Jobs:
    """Every read and write of job records and job states goes through here."""

    def __init__(self, conn: redis.Redis, state_nodes: list[redis.Redis] | None = None,
                 tile_pixels: int | None = None) -> None:
        self.r = conn
        self.leases = Leases(conn)
        self.tiles = TiledState(conn, state_nodes)
        self.images = Images(conn)
        self.tile_pixels = config().tile_pixels if tile_pixels is None else tile_pixels  # of the jobs it creates
        self._set_if_exists = conn.register_script(SET_IF_EXISTS)

    # ------------------------------------------------------------------ records
    def create(self, scene: dict[str, Any] | str, settings: Settings, width: int, height: int,
               scene_name: str | None, max_active: int | None = None, notes: Iterable[str] = ()) -> str:
        """A new queued job; raises JobLimitReached if `max_active` jobs are active. `scene` is
        the scene JSON, as a dict or already encoded (the API's loads encode it off its threads);
        `notes` are written with the record, in the same transaction, as bounded_notes keeps them.
        The settings are stored for the frame (Settings.for_frame): what the job renders with."""
        settings = settings.for_frame(width, height)
        job_id = uuid.uuid4().hex[:16]
        now = time.time()
        fields: Fields = {"status": Status.QUEUED.value, "settings": settings.model_dump_json(),
                  "scene_name": scene_name or "", "width": width, "height": height, "created": now,
                  "passes": 0, "emitted": 0, "next_pass": 0, "pass_seconds": 0.0, "attempts": "{}",
                  "shards": len(self.tiles.nodes), "tile_pixels": self.tile_pixels,
                  "notes": json.dumps(bounded_notes(notes))}
        with self.r.pipeline() as pipe:
            while True:
                try:
                    pipe.watch(keys.ACTIVE)
                    if max_active is not None and pipe.scard(keys.ACTIVE) >= max_active:
                        raise JobLimitReached(f"at most {max_active} jobs may be active at once: retry when one ends")
                    pipe.multi()
                    pipe.hset(keys.job(job_id), mapping=fields)
                    pipe.set(keys.scene(job_id), scene if isinstance(scene, str) else json.dumps(scene))
                    pipe.zadd(keys.JOBS, {job_id: now})
                    pipe.sadd(keys.ACTIVE, job_id)
                    pipe.execute()
                    return job_id
                except redis.WatchError:
                    continue

    def get(self, job_id: str) -> JobRecord | None:
        h = self.r.hgetall(keys.job(job_id))
        return JobRecord.parse(job_id, h) if h else None

    def scene(self, job_id: str) -> dict[str, Any]:
        scene = self.r.get(keys.scene(job_id))
        if scene is None:
            raise KeyError(f"job {job_id} has no scene")
        return json.loads(scene)

    def status(self, job_id: str) -> Status | None:
        s = self.r.hget(keys.job(job_id), "status")
        return Status(text(s)) if s else None

    def ids(self, offset: int = 0, limit: int | None = None, newest_first: bool = False) -> list[str]:
        end = -1 if limit is None else offset + limit - 1
        ids = self.r.zrevrange(keys.JOBS, offset, end) if newest_first else self.r.zrange(keys.JOBS, offset, end)
        return [text(j) for j in ids]

    def count(self) -> int:
        return self.r.zcard(keys.JOBS)

    def active_count(self) -> int:
        return self.r.scard(keys.ACTIVE)

    def active_ids(self) -> list[str]:
        return sorted(text(j) for j in self.r.smembers(keys.ACTIVE))

    def tiling(self, record: JobRecord) -> Tiling:
        return self.tiles.tiling(record.n_pixels, record.shards, record.tile_pixels)

    @staticmethod
    def _finish(pipe: redis.client.Pipeline, job_id: str, status: Status, now: float) -> None:
        """Queue a move to a final status: the slot is freed and every key of the job on the
        main Redis gets its retention time (its tiles get theirs after: `expire_tiles`)."""
        pipe.hset(keys.job(job_id), mapping={"status": status.value, "finished": now})
        pipe.srem(keys.ACTIVE, job_id)
        for key in keys.job_keys(job_id):
            pipe.expire(key, int(config().retention_seconds))

    def expire_tiles(self, job_id: str) -> None:
        record = self.get(job_id)
        if record is not None and record.status in policy.FINAL:
            self.tiles.expire(job_id, self.tiling(record), int(config().retention_seconds))

    def delete(self, job_id: str) -> None:
        """Remove a job and every key it has."""
        record = self.get(job_id)
        if record is not None:
            self.tiles.delete(job_id, self.tiling(record))
        pipe = self.r.pipeline()
        pipe.delete(*keys.job_keys(job_id))
        pipe.zrem(keys.JOBS, job_id)
        pipe.srem(keys.ACTIVE, job_id)
        pipe.execute()

    def prune(self) -> int:
        """Forget ids of jobs whose records expired (retention); returns how many."""
        ids = self.ids()
        pipe = self.r.pipeline()
        for job_id in ids:
            pipe.exists(keys.job(job_id))
        gone = [job_id for job_id, exists in zip(ids, pipe.execute(), strict=True) if not exists]
        if gone:
            self.r.zrem(keys.JOBS, *gone)
            self.r.srem(keys.ACTIVE, *gone)
        return len(gone)

    def history(self, job_id: str) -> list[dict[str, float]]:
        return [json.loads(x) for x in self.r.lrange(keys.history(job_id), 0, -1)]

    def last_error(self, job_id: str) -> dict[str, float] | None:
        last = self.r.lindex(keys.history(job_id), -1)
        return json.loads(last) if last else None

    # -------------------------------------------------------------------- state
    def has_setup(self, record: JobRecord) -> bool:
        return bool(self.r.hget(keys.job(record.id), "setup") == b"1")

    def init_setup(self, record: JobRecord, setup: dict[str, np.ndarray]) -> None:
        """Fix the job's setup arrays (e.g. R0) once: the first writer wins, per tile."""
        self.tiles.init(record.id, self.tiling(record), record.integrator, setup)
        self.r.hset(keys.job(record.id), "setup", "1")

    def published(self, record: JobRecord) -> Published | None:
        """The job's image as its last fold round published it (worker/store/published.py);
        one a restart of the main Redis lost, made from the tiles' state; None before its
        first round."""
        image = self.images.get(record.id)
        if image is not None or record.image_passes == 0:
            return image
        state = self.state(record)
        return Published.of(record.integrator, state) if state is not None else None

    def state(self, record: JobRecord) -> State | None:
        """The job state as folded (this process's overlay, else the tiles' with the accepted
        batches' pending deltas), or None before its first batch fixed the setup arrays."""
        record = self.get(record.id) or record
        if not record.setup:
            return None

        def snapshot() -> Snapshot:
            pipe = self.r.pipeline()  # one transaction: a checkpoint's count moves both at once
            pipe.hgetall(keys.job(record.id))
            pipe.hgetall(keys.tofold(record.id))
            h, tofold = pipe.execute()
            now = JobRecord.parse(record.id, h) if h else record
            return Snapshot(now.folded_emitted, now.folded_passes, now.counters,
                            {b.decode(): json.loads(v) for b, v in tofold.items()})

        return self.tiles.read(record.id, self.tiling(record), record.integrator, snapshot)

    def batch_inputs(self, record: JobRecord) -> Any:
        """What a batch starting now reads: the inputs the last fold round wrote to the
        tiles (with the passes of the state they come from: a batch's first pass takes the
        radius rule for the passes before it that they lack, GatherInputs)."""
        return self.tiles.inputs(record.id, self.tiling(record), record.integrator)

    # ------------------------------------------------------------------ batches
    def allocate(self, job_id: str, pass_seconds: float | None = None, workers: int = 1) -> Batch | None:
        """Reserve the next range of passes, or None if the job takes no more batches
        (`workers`: how many render the job's batches at once, see policy.batch_passes)."""
        key = keys.job(job_id)
        while True:
            try:
                with self.r.pipeline() as pipe:
                    pipe.watch(key)
                    record = self._read(pipe, job_id)
                    elapsed = record.elapsed_seconds()
                    if record.status not in policy.RENDERING or record.stopping or \
                            policy.out_of_time(record.settings, elapsed):
                        return None
                    seconds = pass_seconds or record.pass_seconds
                    now = time.time()
                    due_at = _scored(pipe.zrange(keys.due(job_id), 0, -1, withscores=True))
                    others_due = [due - now for _, due in due_at]
                    n = policy.batch_passes(seconds, record.mean_merge_seconds,
                                            policy.seconds_left(record.settings, elapsed), record.fold_cost,
                                            workers, policy.passes_left(record.settings, record.next_pass), others_due)
                    if n <= 0:
                        return None
                    batch = Batch(job_id, record.next_pass, n)
                    pipe.multi()
                    pipe.hset(key, "next_pass", batch.first + n)
                    Leases.register(pipe, batch, now + n * seconds + record.mean_merge_seconds)
                    pipe.execute()
                    return batch
            except redis.WatchError:
                continue

    def _settled(self, batch: Batch) -> bool:
        """Accepted and not lost: nothing of the batch is left to render."""
        pipe = self.r.pipeline(transaction=False)
        pipe.sismember(keys.merged(batch.job_id), batch.id)
        pipe.sismember(keys.lost(batch.job_id), batch.id)
        merged, lost = pipe.execute()
        return bool(merged) and not lost

    def start(self, batch: Batch, worker: str) -> bool:
        """Take the lease on a batch; False if it is merged (and not lost) or no longer wanted.
        The first batch to start moves the job from queued to running and starts its clock.

        The take is one transaction with its checks (the job renders, the batch is in
        flight): a cancel either comes first and the batch is not started, or finds the batch
        owned and the job keeps its slot (cancel-requested) until the batch is dropped."""
        if self._settled(batch):
            return False
        key, inflight = keys.job(batch.job_id), keys.inflight(batch.job_id)
        with self.r.pipeline() as pipe:
            while True:
                try:
                    pipe.watch(key, inflight)
                    if not pipe.sismember(inflight, batch.id):
                        return False
                    raw = pipe.hget(key, "status")
                    status = Status(text(raw)) if raw else None
                    if status not in policy.RENDERING:  # cancelled, failed or gone meanwhile
                        break
                    pipe.multi()
                    self.leases.take(pipe, batch, worker)
                    if status == Status.QUEUED:
                        pipe.hset(key, mapping={"status": Status.RUNNING.value, "started": time.time()})
                    pipe.execute()
                    self.leases.heartbeat(worker, batch.job_id, batch.id)
                    return True
                except redis.WatchError:
                    continue
        self.drop(batch)
        return False

    def renew(self, batch: Batch, worker: str) -> Status | None:
        """After every pass: extend the lease, beat the worker's heart, and return the job's
        status (RQ's SimpleWorker sends no heartbeat during a job)."""
        pipe = self.r.pipeline()
        self.leases.renew(pipe, batch, worker)
        pipe.hget(keys.job(batch.job_id), "status")
        status = pipe.execute()[-1]
        return Status(text(status)) if status else None

    def is_wanted(self, batch: Batch) -> bool:
        return self.status(batch.job_id) in policy.RENDERING and not self._settled(batch) \
            and self.leases.is_inflight(batch)

    def drop(self, batch: Batch) -> None:
        """Forget a batch that will not be merged (its job ended or was cancelled)."""
        self.leases.drop(batch)
        self.settle(batch.job_id, Status.CANCEL_REQUESTED, Status.CANCELLED)

    def record_failure(self, batch: Batch, message: str) -> bool:
        """Count a failed attempt; after max_attempts the job fails. True if it failed."""
        key = keys.job(batch.job_id)
        attempts = json.loads(self.r.hget(key, "attempts") or b"{}")
        attempts[batch.id] = attempts.get(batch.id, 0) + 1
        self.r.hset(key, "attempts", json.dumps(attempts))
        if attempts[batch.id] >= config().max_attempts:
            self.fail(batch.job_id, message)
            return True
        return False

    # --------------------------------------------------------------- lifecycle
    @staticmethod
    def _read(pipe: redis.client.Pipeline, job_id: str) -> JobRecord:
        """The record, read inside a transaction that WATCHes it."""
        return JobRecord.parse(job_id, pipe.hgetall(keys.job(job_id)))

    def _end(self, job_id: str, allowed: frozenset[Status], final: Status, fields: Fields | None = None,
             idle: bool = False, fold: bool = True) -> bool:
        """Move a job in one of `allowed` to `final`, atomically, once every accepted batch
        is folded (unless `fold` is off) and, if `idle`, nothing is in flight. False if the
        job was not in `allowed` (or, if `idle`, still had batches in flight), or if a lost
        batch is being rendered again (`refill`; a cancelled job's are taken back)."""
        key = keys.job(job_id)
        if self.status(job_id) not in allowed:
            return False
        if not idle:  # no new batches meanwhile, so the folds below catch up with the accepted ones
            self.r.hset(key, "stopping", "1")
        while True:
            if fold:
                self.fold(job_id, wait=True, decide=False, checkpoint=True)
            with self.r.pipeline() as pipe:
                try:
                    pipe.watch(key, keys.tofold(job_id), keys.inflight(job_id), keys.lost(job_id))
                    status = pipe.hget(key, "status")
                    if status is None or Status(text(status)) not in allowed:
                        return False
                    if idle and pipe.scard(keys.inflight(job_id)) > 0:
                        return False
                    if fold and pipe.scard(keys.lost(job_id)) > 0:
                        if final != Status.CANCELLED:  # its refill ends the job (accept: news)
                            if not idle:
                                pipe.multi()
                                pipe.hdel(key, "stopping")
                                pipe.execute()
                            return False
                        self._give_up(pipe, job_id)
                        pipe.execute()
                        continue
                    if fold and pipe.hlen(keys.tofold(job_id)) > 0:
                        continue  # accepted since the fold: fold it too
                    image: Fields = {} if fold else {"image_passes": pipe.hget(key, "folded_passes") or 0}
                    pipe.multi()
                    if fields or image:
                        pipe.hset(key, mapping=(fields or {}) | image)
                    self._finish(pipe, job_id, final, time.time())
                    pipe.execute()
                    break
                except redis.WatchError:
                    continue
        OVERLAYS.drop(job_id)  # not folded (`fold` off): the image is the last checkpoint
        self.expire_tiles(job_id)
        return True

    def settle(self, job_id: str, status: Status, final: Status) -> None:
        """A job in `status` with nothing in flight ends as `final`."""
        self._end(job_id, frozenset({status}), final, idle=True)

    def _transition(self, job_id: str, allowed: frozenset[Status],
                    write: Callable[[redis.client.Pipeline], object]) -> bool:
        """Atomically: if the job's status is one of `allowed`, run the commands `write`
        queues, in one transaction. False if the status was not allowed."""
        with self.r.pipeline() as pipe:
            while True:
                try:
                    pipe.watch(keys.job(job_id))
                    status = pipe.hget(keys.job(job_id), "status")
                    if status is None or Status(text(status)) not in allowed:
                        return False
                    pipe.multi()
                    write(pipe)
                    pipe.execute()
                    return True
                except redis.WatchError:
                    continue

    def converge(self, job_id: str) -> bool:
        """End a running job whose error reached its threshold (everything accepted folded first)."""
        return self._end(job_id, frozenset({Status.RUNNING}), Status.CONVERGED)

    def fail(self, job_id: str, message: str) -> None:
        """Fail the job at once (what was folded stays its image)."""
        self._end(job_id, policy.ACTIVE, Status.FAILED, {"error": message[:2000]}, fold=False)

    def cancel(self, job_id: str) -> Status | None:
        """Request cancellation; returns the resulting status. Batches no worker has taken
        are dropped at once, so a job with nothing rendering ends (and frees its slot) now;
        a worker that takes one of them later finds the job no longer rendering."""
        self._transition(job_id, policy.RENDERING,
                         lambda pipe: pipe.hset(keys.job(job_id), "status", Status.CANCEL_REQUESTED.value))
        for batch in self.leases.unowned(job_id):
            self.leases.drop(batch)
        self.settle(job_id, Status.CANCEL_REQUESTED, Status.CANCELLED)
        return self.status(job_id)

    # -------------------------------------------------------------------- merge
    def merge(self, batch: Batch, delta: Delta, seconds: float, wall_seconds: float | None = None,
              cpu_seconds: float = 0.0) -> str:
        """Push a batch's delta to the job's tiles, then accept it exactly once. Returns
        'merged', 'refilled' (a lost batch's tiles refilled, `refill`), 'duplicate' or
        'inactive'. The batch that ends the job folds everything accepted before the job
        takes its final status. `seconds` and `cpu_seconds` are the render's wall and process
        CPU time, `wall_seconds` the batch's from its lease."""
        key = keys.job(batch.job_id)
        merge_start, merge_cpu = time.perf_counter(), time.process_time()
        record = self.get(batch.job_id)
        if record is None or record.status not in policy.MERGING or self._settled(batch):
            outcome = "duplicate" if record is not None and record.status in policy.MERGING else "inactive"
            self.drop(batch)
            return outcome
        # Push.
        tiling = self.tiling(record)
        self.tiles.push(batch.job_id, tiling, batch.id, delta, record.integrator.sums.half)
        # Accept.
        outcome, final = self.accept(batch, delta, seconds, seconds if wall_seconds is None else wall_seconds,
                                     cpu_seconds)
        if outcome == "refilled":  # counted before; the tiles that folded it before the loss keep theirs
            self.tiles.discard(batch.job_id, tiling, batch.id, folded_only=True)
        elif outcome != "merged":
            self.tiles.discard(batch.job_id, tiling, batch.id, folded_only=outcome == "duplicate")
            self.drop(batch)
            return outcome
        else:
            pipe = self.r.pipeline(transaction=False)  # push and accept
            pipe.hincrbyfloat(key, "merge_seconds", time.perf_counter() - merge_start)
            pipe.hincrbyfloat(key, "merge_cpu_seconds", time.process_time() - merge_cpu)
            pipe.execute()
        if final is not None:
            self._hand_off_end(batch.job_id, final)
        return outcome

    @staticmethod
    def _news(pipe: redis.client.Pipeline, job_id: str) -> None:
        """Queue the news that the job's end is decided: its reducer ends it at once."""
        pipe.lpush(keys.FOLD_NEWS, job_id)
        pipe.ltrim(keys.FOLD_NEWS, 0, keys.FOLD_NEWS_KEPT - 1)

    def _hand_off_end(self, job_id: str, final: Status) -> None:
        """The batch that decided the job's end: the job's reducer ends it (end_if_decided,
        from the image it holds in memory: one delta to add, then the checkpoint); this
        worker ends it itself if no process has begun to within end_handoff_seconds (the
        reducers down or stuck), reading the state and every pending delta from the tiles.

        A folder that holds the job's fold lease is at work, and alive: its lease lapses
        within fold_lease_seconds if it dies. So the hand-off waits end_handoff_seconds from
        when the lease was last seen held, up to the 2 fold_lease_seconds a folder waits for
        the lease (FoldLease). Why wait: a worker that took over would only wait for the
        lease, then rebuild the state the reducer holds in memory."""
        if self.r.scard(keys.lost(job_id)):
            return  # the last lost batch's refill hands it off
        start = time.monotonic()
        deadline, latest = start + config().end_handoff_seconds, start + 2 * config().fold_lease_seconds
        while time.monotonic() < deadline:
            record = self.get(job_id)
            if record is None or record.stopping or record.status not in policy.MERGING:
                return
            if self.r.exists(keys.fold_lock(job_id)):
                deadline = min(latest, max(deadline, time.monotonic() + config().end_handoff_seconds))
            time.sleep(config().end_handoff_poll_seconds)
        self._end(job_id, policy.MERGING, final)

    def wait_for_news(self, seconds: float) -> None:
        """Block until a batch that ends its job is accepted (keys.FOLD_NEWS), at most
        `seconds`: the reducer's final round starts at once, not at its next look."""
        self.r.blpop([keys.FOLD_NEWS], timeout=seconds)

    def end_if_decided(self, job_id: str) -> bool:
        """End a job whose accepted batch decided its final status (its reducer, at
        once: no later batch can add to the round)."""
        record = self.get(job_id)
        if record is None or record.ending is None or record.stopping or self.r.scard(keys.lost(job_id)):
            return False  # (a lost batch's refill brings the news again)
        return self._end(job_id, policy.MERGING, record.ending)

    def accept(self, batch: Batch, delta: Delta, seconds: float, wall_seconds: float,
               cpu_seconds: float = 0.0) -> tuple[str, Status | None]:
        """Count a batch whose delta every tile holds, once: read the record, decide the job's status, write. One
        transaction. Returns the outcome and the final status the batch decided, if any (a
        lost batch's refill: the one decided before, `ending`)."""
        key = keys.job(batch.job_id)
        with self.r.pipeline() as pipe:
            while True:
                try:
                    pipe.watch(key, keys.merged(batch.job_id), keys.lost(batch.job_id))
                    if not pipe.exists(key):
                        return "inactive", None
                    # Read.
                    record = self._read(pipe, batch.job_id)
                    merged = pipe.sismember(keys.merged(batch.job_id), batch.id)
                    if merged and not pipe.sismember(keys.lost(batch.job_id), batch.id):
                        return "duplicate", None
                    if record.status not in policy.MERGING:
                        return "inactive", None
                    if merged:  # a refill: counted already, its lost deltas are back
                        pipe.multi()
                        pipe.srem(keys.lost(batch.job_id), batch.id)
                        Leases.release(pipe, batch)
                        if record.ending is not None:  # it held the job's end back
                            self._news(pipe, batch.job_id)
                        pipe.execute()
                        return "refilled", record.ending
                    # Decide.
                    passes, emitted = record.passes + delta.n_passes, record.emitted + delta.emitted
                    status = policy.after_merge(record.status, record.settings, passes, record.elapsed_seconds())
                    per_pass = seconds / batch.n
                    fields: Fields = {
                        "passes": passes, "emitted": emitted,
                        "pass_seconds": per_pass if record.pass_seconds == 0 else
                        0.7 * record.pass_seconds + 0.3 * per_pass,
                        "render_seconds": record.render_seconds + seconds,
                        "render_cpu_seconds": record.render_cpu_seconds + cpu_seconds, "merges": record.merges + 1,
                        "longest_batch_seconds": max(record.longest_batch_seconds, wall_seconds)}
                    if record.passes <= record.image_passes:  # the first batch the image lacks
                        fields["waiting_since"] = time.time()
                    if status in policy.FINAL:  # whoever ends the job (merge: _hand_off_end) reads it here
                        fields["ending"] = status.value
                    counters = delta.counters
                    # Write.
                    pipe.multi()
                    pipe.hset(key, mapping=fields)
                    pipe.sadd(keys.merged(batch.job_id), batch.id)
                    pipe.hset(keys.tofold(batch.job_id), batch.id,
                              json.dumps({"n": delta.n_passes, "e": delta.emitted, "c": counters}))
                    Leases.release(pipe, batch)
                    if status in policy.FINAL:
                        self._news(pipe, batch.job_id)
                    pipe.execute()
                    return "merged", (status if status in policy.FINAL else None)
                except redis.WatchError:
                    continue

    # --------------------------------------------------------------------- fold
    def fold(self, job_id: str, wait: bool = False, decide: bool = True, checkpoint: bool = False) -> Folded | None:
        """One fold round of the job (worker/reducer.py `fold`, which imports this module)."""
        from worker.reducer import fold

        return fold(self, job_id, wait, decide, checkpoint)

    def note_cost(self, job_id: str, seconds: float) -> None:
        """Record a round's whole length (JobRecord.fold_cost) in the job's record, if it still
        has one (a finished job may be deleted while its last round writes)."""
        self._set_if_exists(keys=[keys.job(job_id)], args=["round_cost", seconds])

    def foldable(self, job_id: str) -> dict[str, dict[str, Any]]:
        """The accepted batches a round can fold (id -> {n, e, c}): all but the lost ones."""
        pipe = self.r.pipeline()
        pipe.hgetall(keys.tofold(job_id))
        pipe.smembers(keys.lost(job_id))
        tofold, lost = pipe.execute()
        return {b.decode(): json.loads(v) for b, v in tofold.items() if b not in lost}

    def refill(self, job_id: str, batch_ids: list[str]) -> None:
        """Mark accepted batches lost and, if the job still renders, issue them again (the
        reaper enqueues them at its next look): same ids, same passes. (A cancelled job takes
        them back: `_end`.)"""
        rendering = self.status(job_id) in policy.RENDERING
        pipe = self.r.pipeline()
        pipe.sadd(keys.lost(job_id), *batch_ids)
        for batch_id in batch_ids if rendering else ():
            Leases.register(pipe, Batch.from_id(job_id, batch_id), due=time.time(), queued=False)
        pipe.execute()
        log.warning("deltas lost by a state node's restart: batches issued again",
                    extra={"job": job_id, "batches": batch_ids})

    def _give_up(self, pipe: redis.client.Pipeline, job_id: str) -> None:
        """Queue taking back the job's lost batches (a cancelled job renders nothing more): no
        longer accepted nor counted (a tile that folded one before the loss keeps it)."""
        lost = [text(b) for b in pipe.smembers(keys.lost(job_id))]
        headers = [json.loads(h) for h in pipe.hmget(keys.tofold(job_id), lost) if h] if lost else []
        pipe.multi()
        if lost:
            pipe.hdel(keys.tofold(job_id), *lost)
            pipe.srem(keys.merged(job_id), *lost)
            pipe.delete(keys.lost(job_id))
            pipe.hincrby(keys.job(job_id), "passes", -sum(h["n"] for h in headers))
            pipe.hincrby(keys.job(job_id), "emitted", -sum(h["e"] for h in headers))
            for batch_id in lost:
                Leases.release(pipe, Batch.from_id(job_id, batch_id))

    def paced(self, record: JobRecord, fresh: set[str],
               accepted: dict[str, Any]) -> tuple[set[str], dict[str, Any]]:
        """The batches new to the image a regular round takes in (policy.paced_batches, given
        when the next in-flight batch is due: the oldest passes first), and the accepted
        batches less those it leaves for later."""
        due = _scored(self.r.zrange(keys.due(record.id), 0, 0, withscores=True))
        take = policy.paced_batches(len(fresh), due[0][1] - time.time() if due else None,
                                    policy.round_seconds(record.fold_rounds, 1) or 0.0)  # None before any round
        later = sorted(fresh, key=lambda b: Batch.from_id(record.id, b).first)[take:]
        return fresh.difference(later), {b: v for b, v in accepted.items() if b not in later}

    @staticmethod
    def _since_fold(record: JobRecord) -> float:
        """Seconds since the job's last fold round (infinite before the first: the first
        image appears as soon as a batch is accepted)."""
        return time.time() - record.folded_at if record.folded_at else float("inf")

    def _next_round(self, record: JobRecord) -> tuple[float, int]:
        """Seconds until the job's next regular round is due (at most 0: due now), `fold_interval`
        after the last round's image for a round of the batches waiting now, and how many of
        those this process's image lacks (lost ones aside: no round can fold them)."""
        fresh = self.foldable(record.id).keys() - OVERLAYS.batches(record.id)
        expected = policy.round_seconds(record.fold_rounds, max(1, len(fresh)))
        return policy.fold_interval(record.fold_cost, expected) - self._since_fold(record), len(fresh)

    def fold_if_due(self, job_id: str) -> Folded | None:
        """The reducer's fold: once `fold_interval`
        has passed since the last round, for a round of the batches waiting now."""
        record = self.get(job_id)
        if record is None or self._next_round(record)[0] > 0.0:
            return None
        return self.fold(job_id)

    def next_round_in(self, job_id: str) -> float | None:
        """Seconds until the job's next regular round is due (at most 0: due now); None with
        no accepted batch that this process's image lacks (the round waits for one)."""
        record = self.get(job_id)
        if record is None:
            return None
        due, fresh = self._next_round(record)
        return due if fresh else None

    def fold_if_stale(self, job_id: str) -> Folded | None:
        """A worker's fold after its merge, if accepted passes have waited for the image
        fold_stale_seconds past the time the reducer plans it (policy.image_due): the reducer is down
        or behind, and the image still refreshes. It checkpoints: a worker serves no image,
        so it keeps no overlay."""
        record = self.get(job_id)
        if record is None or record.passes <= record.image_passes:
            return None
        waiting = time.time() - (record.waiting_since or record.started or time.time())
        if waiting < policy.image_due(record.fold_seconds, record.fold_cost) + config().fold_stale_seconds:
            return None
        return self.fold(job_id, checkpoint=True)
