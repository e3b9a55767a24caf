"""The job state on its nodes: batches push their deltas per tile, a folder adds them in.

A worker never reads or writes the folded state. It pushes its batch's delta, cut into
tiles, into each tile's pending hash (HSET by batch id: a re-pushed batch overwrites its
own entry, never adds a second one), and the job record then accepts the batch
(worker/store/record.py). The folder, whoever holds the job's fold lease (the API's
folder thread, a reader, or a worker when the last fold is stale), folds every accepted
batch it has not folded yet: it takes the state (its overlay, worker/store/overlay.py, or
the last checkpoint, from its cache when the tile's version is unchanged), adds the
round's deltas with the integrator's own merge (one merge per round: a big pass, digest
11.2 (i)) and writes each tile's batch inputs. Now and then a round checkpoints: it writes
each tile in one transaction that WATCHes the tile's version: new state, new batch
inputs, the batches added to the tile's folded set, their pending entries removed. So a
tile takes a batch exactly once, whichever folder gets there, and a folder killed
mid-round leaves each tile either folded or not; the next round folds the rest (tiles
that have the batch skip it).

Deltas stay out of the nodes' append-only files (PUSH): they are the largest part of what
a job writes, and logging them would cost the nodes much of their CPU. Everything that
counts is logged: the record's acceptance, the checkpoints' states, folded sets and
removals. So a node's restart can lose a pending delta of an accepted batch; a fold round
that finds one missing on a tile that has not folded it raises LostDeltas, and the record
has the batch rendered again under its id to refill those tiles (worker/store/record.py).
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Collection, Sequence
from concurrent.futures import ThreadPoolExecutor
from contextlib import AbstractContextManager, nullcontext
from dataclasses import dataclass
from typing import Any

import numpy as np
import redis

from worker.error_estimate import ErrorEstimate
from worker.host_threads import each, threads
from worker.integrators import Integrator
from worker.integrators.base import Delta, State
from worker.stats import add_counts
from worker.store import keys, policy
from worker.store.connection import Fields, binary
from worker.store.overlay import OVERLAYS, Overlay
from worker.store.tiles import (
    CACHE,
    STATE_DTYPE,
    DeltaFormatError,
    Tiling,
    TornInputs,
    decode_delta,
    decode_inputs,
    decode_state,
    encode_delta,
    encode_inputs,
    encode_state,
    state_nodes,
)

# Applies a folded round to the job record once per batch, however many folders try.
ACCOUNT = """
for i = 1, #ARGV do
  local h = redis.call('HGET', KEYS[1], ARGV[i])
  if h then
    local t = cjson.decode(h)
    redis.call('HDEL', KEYS[1], ARGV[i])
    redis.call('HINCRBY', KEYS[2], 'folded_passes', t.n)
    redis.call('HINCRBY', KEYS[2], 'folded_emitted', t.e)
    for name, value in pairs(t.c) do
      redis.call('HINCRBY', KEYS[2], 'counter:' .. name, value)
    end
  end
end
return 1
"""
# A tile's state fields. A state the previous version wrote as one string (every array in
# the state's order, or only the setup arrays before the tile's first fold) becomes the hash
# first, with the same numbers (ARGV: the number of setup arrays, then each array's name and
# bytes over the tile, in the state's order).
READ_STATE = """
if redis.call('TYPE', KEYS[1]).ok == 'string' then
  local blob = redis.call('GET', KEYS[1])
  local setup, at, fields, setup_bytes = tonumber(ARGV[1]), 1, {}, 0
  for i = 1, setup do setup_bytes = setup_bytes + tonumber(ARGV[2 * i + 1]) end
  local count = (#blob == setup_bytes) and setup or (#ARGV - 1) / 2
  for i = 1, count do
    local size = tonumber(ARGV[2 * i + 1])
    table.insert(fields, ARGV[2 * i])
    table.insert(fields, string.sub(blob, at, at + size - 1))
    at = at + size
  end
  redis.call('DEL', KEYS[1])
  redis.call('HSET', KEYS[1], unpack(fields))
end
return redis.call('HGETALL', KEYS[1])
"""
# A batch's delta for one tile, written without a record in the append-only file (nor any
# replica): REPL_NONE. An append-only-file rewrite that runs meanwhile does keep it.
PUSH = """
redis.set_repl(redis.REPL_NONE)
return redis.call('HSET', KEYS[1], ARGV[1], ARGV[2])
"""
# Drops a tile's pending entry of a batch the tile has already folded (a late duplicate).
DISCARD_FOLDED = """
if redis.call('SISMEMBER', KEYS[1], ARGV[1]) == 1 then redis.call('HDEL', KEYS[2], ARGV[1]) end
return 1
"""


# Tiles per round trip to a node, and per transaction of a fold's writes (TiledState._on_versions):
# 4 tiles of state are 36 MB at 136 bytes a pixel.
TILES_PER_TRIP = 4
# A batch's inputs read while a fold round writes them (tiles of two rounds) are read again,
# at most this many times in all, so far apart (a round writes them in milliseconds).
INPUT_READS = 20
INPUT_RETRY_SECONDS = 0.05


def _trips(tiles: list[int]) -> list[list[int]]:
    """`tiles` cut into runs of at most TILES_PER_TRIP, in order."""
    return [tiles[at:at + TILES_PER_TRIP] for at in range(0, len(tiles), TILES_PER_TRIP)]


class FoldContended(Exception):
    """Another folder changed a tile during this round: it has the lease now."""


class LostDeltas(Exception):
    """Accepted batches whose delta is gone from a tile that has not folded them (a state
    node restarted: deltas are not in its append-only file); the round wrote nothing."""

    def __init__(self, batch_ids: list[str]) -> None:
        super().__init__(f"deltas lost: batches {', '.join(batch_ids)}")
        self.batch_ids = batch_ids


class UnreadableDelta(Exception):
    """An accepted batch's delta this folder cannot read (tiles.DeltaFormatError); the round
    wrote nothing."""

    def __init__(self, batch_id: str, message: str) -> None:
        super().__init__(message)
        self.batch_id = batch_id


@dataclass(frozen=True)
class Folded:
    """What a fold round made of the job: its state, the image's error after it, this
    process's CPU seconds per stage of the round (logged; bench/fold_round.py), and whether
    every batch it holds is now written on every tile (a checkpoint: the record counts them)
    or some stay in the folder's memory."""

    state: State
    error: float | None
    stages: dict[str, float]
    checkpointed: bool
    rebuilt: bool = False  # the round read the state from the tiles (no overlay: policy.Round)
    estimate: ErrorEstimate | None = None  # the error per pixel (None: no estimate, or the round added no batch)


@dataclass(frozen=True)
class Snapshot:
    """The record's folded counters (of the batches every tile has written) and the accepted
    batches not yet counted there (id -> {n, e, c}), read at one moment."""

    emitted: int
    passes: int
    counters: dict[str, int]
    accepted: dict[str, dict[str, Any]]


class Stages:
    """CPU seconds of this process per stage, each stage from the last `lap` to the next."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}
        self._at = time.process_time()

    def lap(self, name: str) -> None:
        now = time.process_time()
        self.seconds[name] = self.seconds.get(name, 0.0) + now - self._at
        self._at = now


class TiledState:
    """One process's access to the job states on the state nodes."""

    def __init__(self, main: redis.Redis, nodes: list[redis.Redis] | None = None) -> None:
        self.main = main
        self.nodes = nodes if nodes is not None else state_nodes(main)
        self._account = main.register_script(ACCOUNT)
        self._discard = [node.register_script(DISCARD_FOLDED) for node in self.nodes]
        self._read_state = [node.register_script(READ_STATE) for node in self.nodes]
        self._push = [node.register_script(PUSH) for node in self.nodes]

    def tiling(self, n_pixels: int, shards: int, tile_pixels: int) -> Tiling:
        if shards != len(self.nodes):
            raise RuntimeError(f"the job's state lies on {shards} Redis nodes, this process names "
                               f"{len(self.nodes)} (PHOTONFARM_STATE_URLS)")
        return Tiling(n_pixels, shards, tile_pixels)

    def _per_node(self, tiling: Tiling, work: Callable[[int, list[int]], dict[int, Any]]) -> dict[int, Any]:
        """`work(node, some of its tiles)` for every node's tiles: the nodes at once (a thread
        each, as many as there are nodes: each waits on its own server), and one node's tiles
        in parts on the host threads (worker/host_threads.py: the client's CPU work)."""
        by_node = tiling.by_node()
        parts = max(1, -(-threads() // len(by_node)))
        pieces = [(node, tiles[i::parts]) for node, tiles in by_node.items() for i in range(parts) if tiles[i::parts]]
        if len(by_node) == 1:
            results = each(lambda item: work(*item), pieces)
        else:
            with ThreadPoolExecutor(len(pieces)) as pool:
                results = list(pool.map(lambda item: work(*item), pieces))
        out: dict[int, Any] = {}
        for part in results:
            out |= part
        return out

    def _each_node(self, tiling: Tiling, queue: Any) -> dict[int, list[Any]]:
        """Run `queue(pipe, k)` for every tile, pipelined per node TILES_PER_TRIP tiles at a
        time (a node buffers a trip's requests and replies, which count against its
        memory cap), the nodes at once; results by tile."""
        def trips(node: int, tiles: list[int]) -> dict[int, list[Any]]:
            out: dict[int, list[Any]] = {}
            for ks in _trips(tiles):
                pipe = self.nodes[node].pipeline(transaction=False)
                counts = []
                for k in ks:
                    before = len(pipe)
                    queue(pipe, k)
                    counts.append(len(pipe) - before)
                results = pipe.execute()
                first = 0
                for k, count in zip(ks, counts, strict=True):
                    out[k] = results[first:first + count]
                    first += count
            return out
        return self._per_node(tiling, trips)

    # ------------------------------------------------------------------ setup
    def init(self, job_id: str, tiling: Tiling, integrator: Integrator, setup: dict[str, np.ndarray]) -> None:
        """Write the setup arrays and the first inputs of every tile (the first writer wins,
        per field). A tile's state holds only its setup arrays until its first fold (the sums
        are zero), and they are never written again."""
        state = integrator.start(setup)
        arrays, inputs = state.arrays(), integrator.batch_inputs(state)
        self._each_node(tiling, lambda pipe, k: (
            [pipe.hsetnx(keys.tile(job_id, k, "state"), name, blob)
             for name, blob in encode_state(arrays, list(integrator.setup_arrays), tiling.span(k)).items()],
            pipe.set(keys.tile(job_id, k, "inputs"), encode_inputs(inputs, tiling.span(k)), nx=True)))

    def inputs(self, job_id: str, tiling: Tiling, integrator: Integrator) -> Any:
        """What a batch starting now reads: the inputs the last fold wrote, every tile's of
        the same round (read again while a round writes them; after INPUT_READS reads, as
        they are: a folder killed mid-write leaves them mixed until the next round)."""
        spans = [tiling.span(k) for k in range(tiling.count)]

        def read(whole: bool) -> Any:
            blobs = self._each_node(tiling, lambda pipe, k: pipe.get(keys.tile(job_id, k, "inputs")))
            return decode_inputs([blobs[k][0] for k in range(tiling.count)], spans, tiling.n_pixels,
                                 integrator.inputs_type, whole)

        for _ in range(INPUT_READS - 1):
            try:
                return read(whole=True)
            except TornInputs:
                time.sleep(INPUT_RETRY_SECONDS)
        return read(whole=False)

    # ------------------------------------------------------------------- push
    def push(self, job_id: str, tiling: Tiling, batch_id: str, delta: Delta, half: Collection[str] = ()) -> None:
        """Push a batch's delta, the sums named in `half` in half precision (SumLayout.half)."""
        self.push_encoded(job_id, tiling, batch_id, lambda k: encode_delta(delta.sums, tiling.span(k), half))

    def push_encoded(self, job_id: str, tiling: Tiling, batch_id: str,
                     payload: Callable[[int], bytes | memoryview]) -> None:
        """Write each tile's part of a batch (`payload(k)`, encoded) into its pending hash,
        outside the append-only file (PUSH)."""
        self._each_node(tiling, lambda pipe, k: self._push[tiling.node(k)](
            keys=[keys.tile(job_id, k, "pending")], args=[batch_id, payload(k)], client=pipe))

    def discard(self, job_id: str, tiling: Tiling, batch_id: str, folded_only: bool) -> None:
        """Remove a batch's pending entries: all of them (it was not accepted), or only
        where the tile already folded it (a duplicate of an accepted batch)."""
        for node, ks in tiling.by_node().items():
            pipe = self.nodes[node].pipeline(transaction=False)
            for k in ks:
                pending = keys.tile(job_id, k, "pending")
                if folded_only:
                    self._discard[node](keys=[keys.tile(job_id, k, "folded"), pending], args=[batch_id], client=pipe)
                else:
                    pipe.hdel(pending, batch_id)
            pipe.execute()

    # ------------------------------------------------------------------- read
    def _versions(self, job_id: str, tiling: Tiling,
                  batch_ids: Sequence[str] = ()) -> tuple[dict[int, int], dict[int, list[str]]]:
        """Each tile's version, and the batches of `batch_ids` it has not written (tiles that
        lack none left out)."""
        got = self._each_node(tiling, lambda pipe, k: (
            pipe.hget(keys.tile(job_id, k, "meta"), "version"),
            batch_ids and pipe.smismember(keys.tile(job_id, k, "folded"), list(batch_ids))))
        lacking = {k: [b for b, done in zip(batch_ids, g[1], strict=True) if not done]
                   for k, g in got.items() if batch_ids}
        return {k: int(g[0] or 0) for k, g in got.items()}, {k: ids for k, ids in lacking.items() if ids}

    def _blobs(self, job_id: str, tiling: Tiling, integrator: Integrator,
               versions: dict[int, int]) -> dict[int, Fields]:
        """Each tile's state fields at the version given: from the cache, else read (and checked)."""
        cached = {k: CACHE.get(job_id, k, v) for k, v in versions.items()}
        out = {k: fields for k, fields in cached.items() if fields is not None}
        missing = [k for k in cached if k not in out]
        if missing:
            want = set(missing)

            def layout(k: int) -> list[Any]:  # READ_STATE's ARGV
                size = tiling.span(k).stop - tiling.span(k).start
                return [len(integrator.setup_arrays), *(v for name, w in integrator.state_widths.items()
                                                        for v in (name, STATE_DTYPE.itemsize * size * w))]

            read = self._each_node(tiling, lambda pipe, k: (
                pipe.hget(keys.tile(job_id, k, "meta"), "version"),
                self._read_state[tiling.node(k)](keys=[keys.tile(job_id, k, "state")], args=layout(k), client=pipe))
                if k in want else None)
            for k in missing:
                version, flat = read[k]
                if int(version or 0) != versions[k]:
                    raise FoldContended(f"tile {k} changed while read")
                fields = dict(zip(flat[::2], flat[1::2], strict=True))
                CACHE.put(job_id, k, versions[k], fields)
                out[k] = fields
        return out

    @staticmethod
    def _arrays(tiling: Tiling, integrator: Integrator, blobs: dict[int, Fields]) -> dict[str, np.ndarray]:
        """The whole frame's state arrays from its tiles' fields (an array a tile does not
        hold is zero there)."""
        n, widths = tiling.n_pixels, integrator.state_widths
        arrays = {name: np.zeros((n, w) if w > 1 else n) for name, w in widths.items()}
        for k, fields in blobs.items():
            span = tiling.span(k)
            for name, part in decode_state(fields, widths, span.stop - span.start).items():
                arrays[name][span] = part
        return arrays

    def read(self, job_id: str, tiling: Tiling, integrator: Integrator, snapshot: Callable[[], Snapshot]) -> State:
        """The folded state: this process's overlay if it is on the tiles' versions, else the
        tiles' states with the record's folded counters (`snapshot`, read after the
        versions), plus the accepted batches some tiles have written and others not (a
        checkpoint writes some of the tiles each round, or a folder died mid-checkpoint):
        their counts once, and their pending deltas on the tiles that lack them. A tile that a
        folder writes meanwhile makes the read start again. A delta lost there (a state node
        restarted before the tile's checkpoint, and no folder held the batch: Jobs.fold has it
        rendered again) is left out until its batch is: that tile shows one batch less than
        its counts say for so long."""
        while True:
            try:
                versions, _ = self._versions(job_id, tiling)
                if (held := OVERLAYS.state(job_id, versions)) is not None:
                    return held
                snap = snapshot()
                accepted, batch_ids = snap.accepted, sorted(snap.accepted)
                now, lacking = self._versions(job_id, tiling, batch_ids)
                if now != versions:
                    continue
                blobs = self._blobs(job_id, tiling, integrator, versions)
                state = integrator.restore(self._arrays(tiling, integrator, blobs),
                                           snap.emitted, snap.passes, snap.counters)
                written = [b for b in batch_ids if sum(b in ids for ids in lacking.values()) < tiling.count]
                if written:
                    fresh = {k: [b for b in ids if b in written] for k, ids in lacking.items()}
                    self._add_pending(job_id, tiling, integrator, versions, {k: ids for k, ids in fresh.items() if ids},
                                      [accepted[b] for b in written], state, skip_lost=True)
                return state
            except FoldContended:
                continue

    def _add_pending(self, job_id: str, tiling: Tiling, integrator: Integrator, versions: dict[int, int],
                     fresh: dict[int, list[str]], headers: list[dict[str, Any]],
                     state: State, skip_lost: bool = False) -> tuple[dict[int, int], dict[int, set[str]]]:
        """Merge some accepted batches into `state`: each tile's pending deltas of them
        (`fresh`: tile -> batch ids it has not written), read and added a tile at a time
        straight into the state's pixels (no frame-sized delta: at 3840x2160 that would be
        a GB, allocated and written once more per round), then their headers' passes,
        photons and counters. Returns, per tile, the bytes read and the arrays its deltas
        carried. Every delta is checked readable (UnreadableDelta); a delta gone because its
        tile was written meanwhile raises FoldContended, and one gone with the tile unchanged
        was lost (LostDeltas, after every tile is read; left out with `skip_lost`). Each leaves
        `state` part-merged: the caller drops it."""
        delta_widths = dict(integrator.sums.widths)
        carried: dict[int, set[str]] = {}
        lost: set[str] = set()  # batches with a delta lost on some tile (the nodes' threads add to it)

        def add(node: int, tiles: list[int]) -> dict[int, int]:
            read = {}
            for k in (k for k in tiles if k in fresh):
                span = tiling.span(k)
                payloads = self.nodes[node].hmget(keys.tile(job_id, k, "pending"), fresh[k])
                names = carried.setdefault(k, set())
                for batch_id, payload in zip(fresh[k], payloads, strict=True):
                    if payload is None:
                        if int(self.nodes[node].hget(keys.tile(job_id, k, "meta"), "version") or 0) != versions[k]:
                            raise FoldContended(f"tile {k} was written by another folder")
                        lost.add(batch_id)
                        continue
                    try:
                        parts = decode_delta(binary(payload), delta_widths, span.stop - span.start)
                    except DeltaFormatError as exc:
                        raise UnreadableDelta(batch_id, f"batch {batch_id}, tile {k}: {exc}") from exc
                    integrator.merge_sums(state, parts, span)  # tiles are disjoint: threads never add to one pixel
                    names.update(parts)
                read[k] = sum(len(p) for p in payloads if p is not None)
            return read

        read = self._per_node(tiling, add)
        if lost and not skip_lost:
            raise LostDeltas(sorted(lost))
        added: dict[str, int] = {}
        for header in headers:
            for name, value in header["c"].items():
                added[name] = added.get(name, 0) + int(value)
        add_counts(state, sum(h["n"] for h in headers), sum(h["e"] for h in headers), added)
        return read, carried

    # ------------------------------------------------------------------- fold
    def _on_versions(self, node: int, job_id: str, versions: dict[int, int],
                     queue: Callable[[redis.client.Pipeline, int], Any], until: float | None = None) -> list[int]:
        """Write some of one node's tiles, TILES_PER_TRIP to a transaction: the commands
        `queue(pipe, k)` adds for each tile k, if every tile of the transaction is still at its
        version in `versions` (a WATCH on each); FoldContended if another folder wrote one
        first. A tile's commands always share one transaction. A few tiles to a transaction,
        not one each, because the node writes and fsyncs its append-only file once per
        transaction. No transaction starts that would end after `until` (epoch seconds) if it
        took as long as the longest one so far. Returns the tiles written."""
        written: list[int] = []
        longest = 0.0
        for trip in _trips(list(versions)):
            start = time.time()
            if until is not None and start + longest >= until:
                break
            metas = {k: keys.tile(job_id, k, "meta") for k in trip}
            with self.nodes[node].pipeline() as pipe:
                try:
                    pipe.watch(*metas.values())
                    for k, meta in metas.items():
                        if int(pipe.hget(meta, "version") or 0) != versions[k]:
                            raise FoldContended(f"tile {k} was folded by another folder")
                    pipe.multi()
                    for k in metas:
                        queue(pipe, k)
                    pipe.execute()
                except redis.WatchError as exc:
                    raise FoldContended(f"tiles {list(metas)} were folded by another folder") from exc
            written += trip
            longest = max(longest, time.time() - start)
        return written

    def _rewriting(self, node: int) -> bool:
        """The node is rewriting its append-only file, when writes to it are slower (the
        server writes and fsyncs the rewrite's tail in its main thread). False where the
        node does not say (INFO refused)."""
        try:
            return bool(self.nodes[node].info("persistence").get("aof_rewrite_in_progress"))
        except redis.ResponseError:
            return False

    def fold_round(self, job_id: str, tiling: Tiling, integrator: Integrator, emitted: int, passes: int,
                   counters: dict[str, int], accepted: dict[str, dict[str, Any]],
                   checkpoint: bool = False) -> tuple[Folded, list[int]]:
        """Fold the accepted batches (id -> {n, e, c}; at least one) not yet in this process's
        overlay into it and show the new overlay to this process's readers. `emitted`,
        `passes` and `counters` are the record's folded counters (of the batches every tile
        has written). Returns the round and the tiles whose state is to be written now (every
        tile with `checkpoint`, else policy.checkpoint_tiles): once the image is shown the
        caller runs `write_inputs`, then `checkpoint`. Raises FoldContended if another
        folder got to a tile first."""
        batch_ids = sorted(accepted)
        stages = Stages()
        # Read: versions, which tiles have not written which batch, the state (the overlay's
        # if it was built on these versions, else the tiles').
        versions, todo = self._versions(job_id, tiling, batch_ids)
        overlay = OVERLAYS.valid(job_id, versions)
        if overlay is not None and not overlay.batches <= accepted.keys():
            overlay = None  # cannot happen while the versions hold (a batch is settled once every tile wrote it)
        held = overlay.batches if overlay is not None else frozenset()
        fresh = {k: [b for b in ids if b not in held] for k, ids in todo.items()}
        fresh = {k: ids for k, ids in fresh.items() if ids}
        fresh_ids = [b for b in batch_ids if b not in held]
        if overlay is None:
            arrays = self._arrays(tiling, integrator, self._blobs(job_id, tiling, integrator, versions))
            merging: AbstractContextManager[State] = nullcontext(integrator.restore(arrays, emitted, passes, counters))
        elif fresh_ids:  # the overlay's own state if no reader holds it (its readers wait for this round), else a copy
            merging = OVERLAYS.merging(job_id, overlay, integrator)
        else:
            merging = nullcontext(overlay.state)
        with merging as state:
            stages.lap("read state")
            # Merge the round's deltas: each tile's batches it has not written and the overlay lacks.
            read, carried = self._add_pending(job_id, tiling, integrator, versions, fresh,
                                              [accepted[b] for b in fresh_ids], state) if fresh_ids else ({}, {})
            stages.lap("read and merge deltas")
            # The error.
            error: float | None
            estimate: ErrorEstimate | None = None
            if fresh_ids:
                estimate = integrator.estimate(state)
                error = estimate.average if estimate is not None else None
            else:  # a checkpoint of the overlay as it was (without an overlay every batch is fresh)
                assert overlay is not None, "without an overlay every batch is fresh"
                error = overlay.error
            stages.lap("estimate")
            sent = {k: set(names) for k, names in (overlay.sent if overlay is not None else {}).items()}
            pending = dict(overlay.pending) if overlay is not None else {}
            for k, n in read.items():
                sent.setdefault(k, set()).update(carried[k])
                pending[k] = pending.get(k, 0) + n
            now = time.monotonic()
            now_held = Overlay(versions, held | frozenset(fresh_ids), state, error,
                               {k: frozenset(names) for k, names in sent.items()}, pending,
                               (overlay.folded_at if overlay is not None else {}) | {b: now for b in fresh_ids})
            # Show the image: this process's readers take the overlay.
            OVERLAYS.put(job_id, now_held)
            return (Folded(state, error, stages.seconds, False, rebuilt=overlay is None, estimate=estimate),
                    list(range(tiling.count)) if checkpoint else now_held.checkpoint_tiles(tiling))

    def write_inputs(self, job_id: str, tiling: Tiling, integrator: Integrator) -> dict[str, float]:
        """Write what the next batches read, from this process's overlay of the job (the
        round just made it), into every tile, a few tiles to a transaction on the versions
        the overlay was built on (the nodes at once). After the image: a batch that starts
        meanwhile reads the last round's inputs, as one that started a moment earlier did
        (its first pass takes the radius rule for the passes they lack), and the image does
        not wait for a write through the nodes' append-only files. Returns this process's CPU seconds per
        stage; raises FoldContended (the overlay dropped) if another folder got to a tile first."""
        stages = Stages()
        overlay = OVERLAYS.current(job_id)
        if overlay is None:
            raise FoldContended("this process holds no overlay of the job")
        inputs = integrator.batch_inputs(overlay.state)
        stages.lap("inputs")

        def write(node: int, tiles: list[int]) -> dict[int, None]:
            self._on_versions(node, job_id, {k: overlay.versions[k] for k in tiles}, lambda pipe, k: pipe.set(
                keys.tile(job_id, k, "inputs"), encode_inputs(inputs, tiling.span(k))))
            return {}

        try:
            self._per_node(tiling, write)
        except FoldContended:
            OVERLAYS.drop(job_id)
            raise
        stages.lap("write inputs")
        return stages.seconds

    def checkpoint(self, job_id: str, tiling: Tiling, integrator: Integrator,
                   tiles: list[int], keep: bool = True, until: float | None = None) -> tuple[Overlay, list[str]]:
        """Write this process's overlay of the job (the round just made it) to those of
        `tiles` that lack some of its batches, each tile in one transaction on the version
        the overlay was built on: its state, its folded set, its pending entries gone, its
        version bumped; with `until` (epoch seconds), those policy.checkpoint_required asks
        for and then the others only until then, and none on a node rewriting its
        append-only file (`_rewriting`): the rest stay pending for a later round.
        Returns the overlay on the tiles' new versions (with the batches some tile still
        lacks) and the batches every tile has now written (for the record to count). Run
        inside OVERLAYS.writing (readers keep the overlay while the versions move); raises
        FoldContended if another folder got to a tile first.
        The tile cache takes the state only from a checkpoint whose caller drops the overlay
        (`keep` False: a job's last round, a worker's), every tile at its new version: views
        of the arrays, which no round changes once the overlay is gone. A kept overlay serves
        this process's reads itself, and the next round may add to its state in place
        (Overlays.merging), which a cache entry's view would forbid."""
        overlay = OVERLAYS.current(job_id)
        if overlay is None:
            raise FoldContended("this process holds no overlay of the job")
        batch_ids = sorted(overlay.batches)
        if not batch_ids:
            if not keep:
                self._cache_state(job_id, tiling, integrator, overlay.state, overlay.versions)
            return overlay, []
        _, todo = self._versions(job_id, tiling, batch_ids)
        order = [k for k in tiles if k in todo]
        widths, arrays = integrator.state_widths, overlay.state.arrays()
        # What each tile writes: the arrays its deltas carried and what the merge derives from
        # them (e.g. N); a merge changes nothing where a delta is zero, and the setup arrays
        # (e.g. R0) never change.
        derived = [name for name in widths if name not in integrator.sums.names and name not in integrator.setup_arrays]

        def queue(pipe: redis.client.Pipeline, k: int) -> None:
            sent = overlay.sent.get(k, frozenset())
            fields = encode_state(arrays, [name for name in widths if name in sent] + (derived if sent else []),
                                  tiling.span(k))
            if fields:
                pipe.hset(keys.tile(job_id, k, "state"), mapping=fields)
            pipe.sadd(keys.tile(job_id, k, "folded"), *todo[k])
            pipe.hdel(keys.tile(job_id, k, "pending"), *todo[k])
            pipe.hincrby(keys.tile(job_id, k, "meta"), "version", 1)

        def writer(some: list[int], deadline: float | None) -> Callable[[int, list[int]], dict[int, None]]:
            def write(node: int, node_tiles: list[int]) -> dict[int, None]:  # in the order of `some`
                mine = set(node_tiles)
                versions = {k: overlay.versions[k] for k in some if k in mine}
                return dict.fromkeys(self._on_versions(node, job_id, versions, queue, deadline))
            return write

        # Write: the tiles required whatever the time, then the rest until `until`, on the
        # nodes not rewriting their append-only file.
        required = order if until is None else policy.checkpoint_required(order, overlay.pending,
                                                                            overlay.state_bytes(tiling))
        chosen = set(self._per_node(tiling, writer(required, None)))
        if len(required) < len(order):
            rewriting = {node for node in tiling.by_node() if self._rewriting(node)}  # one question a node
            optional = [k for k in order[len(required):] if tiling.node(k) not in rewriting]
            chosen |= set(self._per_node(tiling, writer(optional, until)))
        left = {k: ids for k, ids in todo.items() if k not in chosen}
        complete = [b for b in batch_ids if not any(b in ids for ids in left.values())]
        versions = {k: v + (k in chosen) for k, v in overlay.versions.items()}
        if not keep:
            self._cache_state(job_id, tiling, integrator, overlay.state, versions)
        return Overlay(versions, overlay.batches - frozenset(complete), overlay.state, overlay.error,
                       {k: v for k, v in overlay.sent.items() if k in left},
                       {k: v for k, v in overlay.pending.items() if k in left},
                       {b: t for b, t in overlay.folded_at.items() if b not in complete}), complete

    @staticmethod
    def _cache_state(job_id: str, tiling: Tiling, integrator: Integrator, state: State,
                     versions: dict[int, int]) -> None:
        """Every tile's state fields into the tile cache at its version (views of `state`)."""
        arrays, names = state.arrays(), list(integrator.state_widths)
        for k in range(tiling.count):
            CACHE.put(job_id, k, versions[k], encode_state(arrays, names, tiling.span(k)))

    def publish(self, job_id: str, folded: Folded, history: dict[str, Any], rounds: Sequence[tuple],
                read_at: float) -> None:
        """After a round: log the error after it, and when it ended, the job's recent rounds
        (policy.Round; this one last), the passes its image holds and since when
        batches it did not see (accepted after `read_at`) wait."""
        pipe = self.main.pipeline()
        pipe.hset(keys.job(job_id), mapping={"folded_at": time.time(), "fold_rounds": json.dumps(rounds),
                                             "image_passes": folded.state.passes, "waiting_since": read_at})
        pipe.rpush(keys.history(job_id), json.dumps(history))
        pipe.execute()

    def settle(self, job_id: str, batch_ids: list[str]) -> None:
        """After a checkpoint: count the batches every tile has now written in the record's
        folded counters, once each, and take them off the batches to fold."""
        self._account(keys=[keys.tofold(job_id), keys.job(job_id)], args=batch_ids)

    # --------------------------------------------------------------- lifetime
    def expire(self, job_id: str, tiling: Tiling, seconds: int) -> None:
        self._each_node(tiling, lambda pipe, k: [pipe.expire(key, seconds) for key in keys.tile_keys(job_id, k)])

    def delete(self, job_id: str, tiling: Tiling) -> None:
        self._each_node(tiling, lambda pipe, k: pipe.delete(*keys.tile_keys(job_id, k)))
