"""The job state sharded over three redis-servers (tiles spread over the nodes, records
and queues on the main one): shuffled concurrent merges with folds racing the pushes, a
worker SIGKILLed while pushing, a folder SIGKILLed mid-round. Every batch counts once in
the record and folds once into every tile; the folded state equals the sum of the
deltas as sent (float32, worker/store/tiles.py), and each tile stores only the arrays its
deltas carried (with N and R0). (The fault tests over HTTP run on sharded state too: api_tests/test_faults.py.)"""

from __future__ import annotations

import dataclasses
import multiprocessing as mp
import os
import pickle
import random
import signal
import threading
import time
import weakref
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest
import redis

from service.redis_server import EmbeddedRedis
from tests.embedded_redis import redis_servers
from tests.helpers import BATCHES, SHARDS, assert_folded_once, caustics_job, merge_new, sharded_store
from worker import stats
from worker.config import Config, config, use
from worker.integrators import integrator_for
from worker.integrators.base import Delta, State
from worker.store import Batch, Jobs, keys, policy
from worker.store import overlay as overlay_module
from worker.store import state as state_module
from worker.store.policy import Status
from worker.store.state import TiledState
from worker.store.tiles import encode_inputs

PROCESSES = 4


@pytest.fixture(scope="module")
def servers(tmp_path_factory: pytest.TempPathFactory) -> Iterator[list[EmbeddedRedis]]:
    with redis_servers(tmp_path_factory.mktemp("sharded"), 1 + SHARDS) as started:
        yield started


def _fresh_job(servers: list[EmbeddedRedis], deltas: tuple, n: int) -> tuple[Jobs, str, list[Delta]]:
    """A new running job on the servers, and the first n of the module's deltas."""
    path, scene, settings, r0 = deltas
    store = sharded_store([s.url for s in servers])
    return store, caustics_job(store, scene, settings, r0), pickle.loads(path.read_bytes())[:n]


def _merge_and_fold(urls: list[str], job_id: str, deltas_file: str, order_seed: int) -> list[str]:
    made: list[Delta] = pickle.loads(Path(deltas_file).read_bytes())
    store = sharded_store(urls)
    order = list(range(len(made)))
    random.Random(order_seed).shuffle(order)
    outcomes = []
    for n, i in enumerate(order):
        outcomes.append(store.merge(Batch(job_id, made[i].first_pass, made[i].n_passes), made[i], 0.1))
        # Folds race the other processes' pushes and folds: rounds in memory (each process its
        # own overlay) and checkpoints, which make the other processes' overlays stale.
        store.fold(job_id, checkpoint=(n + order_seed) % 3 == 0)
    return outcomes


def test_concurrent_shuffled_merges_fold_once_per_tile(servers: list[EmbeddedRedis], deltas: tuple) -> None:
    path, scene, settings, r0 = deltas
    urls = [s.url for s in servers]
    store = sharded_store(urls)
    job_id = caustics_job(store, scene, settings, r0)
    with mp.get_context("spawn").Pool(PROCESSES) as pool:
        outcomes = pool.starmap(_merge_and_fold, [(urls, job_id, str(path), p) for p in range(PROCESSES)])
    flat = [o for per_process in outcomes for o in per_process]
    assert flat.count("merged") == BATCHES and flat.count("duplicate") == (PROCESSES - 1) * BATCHES
    assert_folded_once(store, job_id, pickle.loads(path.read_bytes()))


def _push_then_die(urls: list[str], job_id: str, deltas_file: str, nodes_before_kill: int) -> None:
    """Merge batch 0, SIGKILLed after pushing to `nodes_before_kill` of the nodes (all of
    them: killed before its acceptance)."""
    made: list[Delta] = pickle.loads(Path(deltas_file).read_bytes())
    pushed = []
    real = TiledState._each_node

    def each_node(self, tiling, queue):
        node_of = {k: tiling.node(k) for k in range(tiling.count)}

        def counted(pipe, k):
            if node_of[k] not in pushed:
                if len(pushed) == nodes_before_kill:
                    os.kill(os.getpid(), signal.SIGKILL)
                pushed.append(node_of[k])
            return queue(pipe, k)
        return real(self, tiling, counted)

    TiledState._each_node = each_node
    Jobs.accept = lambda *args: os.kill(os.getpid(), signal.SIGKILL)  # pushed everywhere: dies before accepting
    sharded_store(urls).merge(Batch(job_id, made[0].first_pass, made[0].n_passes), made[0], 0.1)


@pytest.mark.parametrize("nodes_before_kill", [1, SHARDS])
def test_a_worker_killed_while_pushing_counts_its_batch_once(servers: list[EmbeddedRedis], deltas: tuple,
                                                               nodes_before_kill: int) -> None:
    path, scene, settings, r0 = deltas
    urls = [s.url for s in servers]
    store = sharded_store(urls)
    job_id = caustics_job(store, scene, settings, r0)
    child = mp.get_context("spawn").Process(target=_push_then_die, args=(urls, job_id, str(path), nodes_before_kill))
    child.start()
    child.join(120)
    assert child.exitcode == -signal.SIGKILL
    made: list[Delta] = pickle.loads(path.read_bytes())
    first = Batch(job_id, made[0].first_pass, made[0].n_passes)
    assert not store.r.sismember(keys.merged(job_id), first.id)  # never accepted
    # The re-issued batch (the same passes) and the rest; a second copy of batch 0 is a duplicate.
    assert [store.merge(Batch(job_id, d.first_pass, d.n_passes), d, 0.1) for d in made[:3]] == ["merged"] * 3
    assert store.merge(first, made[0], 0.1) == "duplicate"
    assert_folded_once(store, job_id, made[:3])


def _fold_then_die(urls: list[str], job_id: str, tiles_before_kill: int, checkpoint: bool) -> None:
    """One fold round, SIGKILLed mid-write: with `checkpoint`, once the first transaction of
    its checkpoint (a node's tiles, after every tile's inputs) is written and before any
    other node's, the record counting nothing; else as it encodes its (tiles_before_kill +
    1)-th tile's inputs."""
    if checkpoint:
        real_checkpoint, real_write = state_module.TiledState.checkpoint, state_module.TiledState._on_versions
        one_at_a_time, checkpointing = threading.Lock(), threading.Event()

        def checkpoint_then_die(self, *args, **kwargs):
            checkpointing.set()
            return real_checkpoint(self, *args, **kwargs)

        def write(self, *args):
            if not checkpointing.is_set():  # the inputs
                return real_write(self, *args)
            with one_at_a_time:  # the first node's transaction alone, then the end
                real_write(self, *args)
                os.kill(os.getpid(), signal.SIGKILL)

        state_module.TiledState.checkpoint = checkpoint_then_die
        state_module.TiledState._on_versions = write
    else:
        real, spans = state_module.encode_inputs, []

        def encode_inputs(*args):
            if args[-1] not in spans:
                spans.append(args[-1])
                if len(spans) == tiles_before_kill + 1:
                    os.kill(os.getpid(), signal.SIGKILL)
            return real(*args)

        state_module.encode_inputs = encode_inputs
    # a round in memory unless told to checkpoint
    use(dataclasses.replace(config(), checkpoint_pending_share=float("inf")))
    sharded_store(urls).fold(job_id, checkpoint=checkpoint)


@pytest.mark.parametrize("checkpoint", [True, False])
def test_a_folder_killed_mid_round_folds_each_tile_once(servers: list[EmbeddedRedis], deltas: tuple,
                                                         monkeypatch: pytest.MonkeyPatch, checkpoint: bool) -> None:
    path, scene, settings, r0 = deltas
    urls = [s.url for s in servers]
    store = sharded_store(urls)
    job_id = caustics_job(store, scene, settings, r0)
    made: list[Delta] = pickle.loads(path.read_bytes())[:4]
    for d in made:
        assert store.merge(Batch(job_id, d.first_pass, d.n_passes), d, 0.1) == "merged"
    monkeypatch.setenv("PHOTONFARM_LEASE_SECONDS", "2")  # the dead folder's lease lapses soon
    child = mp.get_context("spawn").Process(target=_fold_then_die, args=(urls, job_id, 3, checkpoint))
    child.start()
    child.join(120)
    assert child.exitcode == -signal.SIGKILL
    record = store.get(job_id)
    tiling = store.tiling(record)
    versions = _tile_versions(store, job_id)
    if checkpoint:  # the folder died once one node's transaction (its two tiles) was written
        assert sorted(versions) == [0, 0, 0, 0, 1, 1], versions
        assert all(len({versions[k] for k in ks}) == 1 for ks in tiling.by_node().values()), versions
    else:  # a round in memory writes only the inputs: the tiles are as the last checkpoint left them
        assert set(versions) == {0}, versions
    assert record.folded_passes == 0 and store.r.hlen(keys.tofold(job_id)) == 4
    assert store.fold(job_id, wait=True) is not None  # after its lease lapsed, the next folder
    assert_folded_once(store, job_id, made)


def test_an_overlay_is_dropped_once_another_folder_checkpoints(servers: list[EmbeddedRedis], deltas: tuple) -> None:
    """A round in memory serves its image here and leaves the record's folded counters; a
    checkpoint by another process makes that overlay stale, and the next round here starts
    from the checkpoint: every batch still folds once."""
    store, job_id, made = _fresh_job(servers, deltas, 4)
    for d in made[:2]:
        merge_new(store, job_id, d)
    folded = store.fold(job_id)
    assert folded is not None and not folded.checkpointed
    record = store.get(job_id)
    assert record.folded_passes == 0 and record.image_passes == 4 == store.state(record).passes
    assert store.fold(job_id) is None  # nothing new, and no checkpoint due
    child = mp.get_context("spawn").Process(target=_merge_and_checkpoint,
                                            args=([s.url for s in servers], job_id, str(deltas[0]), 2))
    child.start()
    child.join(120)
    assert child.exitcode == 0
    assert store.get(job_id).folded_passes == 6
    merge_new(store, job_id, made[3])
    folded = store.fold(job_id)
    assert folded is not None and not folded.checkpointed and folded.state.passes == 8
    assert_folded_once(store, job_id, made)


def test_a_checkpoint_writes_a_nodes_tiles_together_or_not_at_all(servers: list[EmbeddedRedis],
                                                                   deltas: tuple) -> None:
    """A checkpoint writes a node's tiles a few to a transaction (the node fsyncs its
    append-only file once per transaction). Where another folder wrote one of them first,
    none of that transaction's tiles is written (here node 0's second tile; the first one,
    written alone before, then held the batch in a state no record counts), the other
    nodes' are, and the next rounds fold the batch once into every tile."""
    store, job_id, made = _fresh_job(servers, deltas, 1)
    merge_new(store, job_id, made[0])
    assert store.fold(job_id) is not None  # a round in memory, no tile written (its delta is under half the state)
    record = store.get(job_id)
    tiling = store.tiling(record)
    assert overlay_module.OVERLAYS.current(job_id).versions == {k: 0 for k in range(tiling.count)}
    first, second = tiling.by_node()[0]
    assert state_module.TILES_PER_TRIP >= 2  # both in one transaction
    node = store.tiles.nodes[0]
    node.hincrby(keys.tile(job_id, second, "meta"), "version", 1)  # another folder's checkpoint of it
    with pytest.raises(state_module.FoldContended), overlay_module.OVERLAYS.writing(job_id):
        store.tiles.checkpoint(job_id, tiling, record.integrator, list(range(tiling.count)))
    for k in range(tiling.count):
        written = store.tiles.nodes[tiling.node(k)].scard(keys.tile(job_id, k, "folded"))
        assert written == (0 if k in (first, second) else len(made)), k
    node.hincrby(keys.tile(job_id, second, "meta"), "version", -1)  # as it was: no other folder wrote it
    assert_folded_once(store, job_id, made)


def _merge_and_checkpoint(urls: list[str], job_id: str, deltas_file: str, i: int) -> None:
    store = sharded_store(urls)
    merge_new(store, job_id, pickle.loads(Path(deltas_file).read_bytes())[i])
    assert store.fold(job_id, wait=True, checkpoint=True).checkpointed


def test_an_overlay_checkpoints_when_old_or_holding_too_many_deltas(servers: list[EmbeddedRedis], deltas: tuple,
                                                                    tune: Callable[..., Config]) -> None:
    """policy.checkpoint_due: by the overlay's age and by the bytes of the deltas it keeps
    pending on the tiles, at the next round with a new batch (none runs for a checkpoint
    alone)."""
    store, job_id, made = _fresh_job(servers, deltas, 3)
    merge_new(store, job_id, made[0])
    assert not store.fold(job_id).checkpointed
    tune(checkpoint_seconds=0.0)
    assert store.fold(job_id) is None  # due, but nothing new to show
    merge_new(store, job_id, made[1])
    folded = store.fold(job_id)
    assert folded is not None and folded.checkpointed
    assert store.get(job_id).folded_passes == made[0].n_passes + made[1].n_passes
    assert not store.r.exists(keys.tofold(job_id))
    tune(checkpoint_seconds=3600.0, checkpoint_pending_share=1e-9)  # any delta kept pending is too much
    merge_new(store, job_id, made[2])
    assert store.fold(job_id).checkpointed
    assert_folded_once(store, job_id, made)


def test_a_checkpoint_round_shows_its_image_before_it_writes_the_state(servers: list[EmbeddedRedis], deltas: tuple,
                                                                        monkeypatch: pytest.MonkeyPatch,
                                                                        tune: Callable[..., Config]) -> None:
    """The long part of a big frame's round, the checkpoint, comes after the image: the
    record already names the round's passes, and this process's readers keep the overlay
    while the tiles' versions move (never a mix of written and unwritten tiles with the
    last checkpoint's counters). After it the overlay goes on, on the new versions, and
    the next read needs no tile."""
    store, job_id, made = _fresh_job(servers, deltas, 3)
    merge_new(store, job_id, made[0])
    assert not store.fold(job_id).checkpointed
    seen: list[tuple[int, int, float]] = []  # during the write: the record's image passes, a read's passes and sum
    real = state_module.encode_state

    def encode_state(arrays, names, span):
        record = store.get(job_id)
        state = store.state(record)
        seen.append((record.image_passes, state.passes, float(sum(a.sum() for a in state.arrays().values()))))
        return real(arrays, names, span)

    monkeypatch.setattr(state_module, "encode_state", encode_state)
    tune(checkpoint_pending_share=1e-9)  # this round checkpoints
    merge_new(store, job_id, made[1])
    folded = store.fold(job_id)
    assert folded is not None and folded.checkpointed
    passes = made[0].n_passes + made[1].n_passes
    total = float(sum(a.sum() for a in folded.state.arrays().values()))
    assert len(seen) == 6  # each tile's state, written (the kept overlay serves reads: nothing cached)
    assert all(s == (passes, passes, total) for s in seen), seen
    monkeypatch.setattr(state_module, "encode_state", real)
    record = store.get(job_id)
    assert record.folded_passes == passes and not store.r.exists(keys.tofold(job_id))
    monkeypatch.setattr(state_module.TiledState, "_blobs", lambda *args: pytest.fail("read the tiles"))
    assert store.state(record) is folded.state  # the overlay, on the tiles' new versions
    merge_new(store, job_id, made[2])
    assert store.fold(job_id).state.passes == passes + made[2].n_passes
    monkeypatch.undo()
    assert_folded_once(store, job_id, made)


def test_a_round_shows_its_image_before_it_writes_the_batch_inputs(servers: list[EmbeddedRedis], deltas: tuple,
                                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    """The image does not wait for the inputs' write (100 MB through the append-only files
    at 3840x2160): while a round writes them, the record names its passes and a reader
    here gets its state, and a batch reads the last round's inputs. Where another folder
    wrote a tile first, the write fails, the overlay is dropped, and the next round folds
    from the tiles: every batch still folds once."""
    store, job_id, made = _fresh_job(servers, deltas, 3)
    merge_new(store, job_id, made[0])
    store.fold(job_id)
    before = store.batch_inputs(store.get(job_id))
    seen: list[tuple[int, int, int]] = []  # as the write starts: the record's image passes, a read's, the inputs'
    real_write = state_module.TiledState.write_inputs

    def observed(self, *args):
        record = store.get(job_id)
        seen.append((record.image_passes, store.state(record).passes, store.batch_inputs(record).passes))
        return real_write(self, *args)

    monkeypatch.setattr(state_module.TiledState, "write_inputs", observed)
    merge_new(store, job_id, made[1])
    folded = store.fold(job_id)
    passes = made[0].n_passes + made[1].n_passes
    assert folded is not None and folded.state.passes == passes and "write inputs" in folded.stages
    assert seen == [(passes, passes, before.passes)]
    assert store.batch_inputs(store.get(job_id)).passes == passes  # written once the round is done
    # Another folder's checkpoint of tile 1 lands between the image and the inputs' write.
    record = store.get(job_id)
    tiling = store.tiling(record)
    node, meta = store.tiles.nodes[tiling.node(1)], keys.tile(job_id, 1, "meta")

    def contended(self, *args):
        node.hincrby(meta, "version", 1)
        return real_write(self, *args)

    monkeypatch.setattr(state_module.TiledState, "write_inputs", contended)
    merge_new(store, job_id, made[2])
    folded = store.fold(job_id)
    assert folded is not None and folded.state.passes == passes + made[2].n_passes
    assert overlay_module.OVERLAYS.current(job_id) is None  # dropped: built on the old version
    monkeypatch.undo()
    node.hincrby(meta, "version", -1)  # as it was: no other folder wrote it
    assert_folded_once(store, job_id, made)


def test_a_round_adds_to_the_overlay_in_place_unless_a_reader_holds_its_state(
        servers: list[EmbeddedRedis], deltas: tuple, monkeypatch: pytest.MonkeyPatch) -> None:
    """A round in memory adds its batches to the overlay's own state when no one else refers
    to it (no copy of the state a round), and to a copy while a reader holds it: the
    reader's state keeps the passes and the numbers it was given."""
    store, job_id, made = _fresh_job(servers, deltas, 3)
    monkeypatch.setattr(overlay_module.policy, "checkpoint_tiles", lambda *args: [])  # every round in memory
    merge_new(store, job_id, made[0])
    assert not store.fold(job_id).checkpointed
    held = store.state(store.get(job_id))  # a reader holds the state
    seen = (held.passes, {name: a.copy() for name, a in held.arrays().items()})
    merge_new(store, job_id, made[1])
    folded = store.fold(job_id)
    assert folded.state is not held and folded.state.passes == made[0].n_passes + made[1].n_passes
    assert held.passes == seen[0] and all(np.array_equal(a, seen[1][name]) for name, a in held.arrays().items())
    previous = weakref.ref(folded.state)  # refers to it without holding it
    del held, folded
    merge_new(store, job_id, made[2])
    folded = store.fold(job_id)
    assert folded.state is previous() and folded.state.passes == sum(d.n_passes for d in made)  # in place
    del folded
    assert_folded_once(store, job_id, made)


def test_a_jobs_last_round_leaves_its_state_to_the_tile_cache(servers: list[EmbeddedRedis], deltas: tuple,
                                                             monkeypatch: pytest.MonkeyPatch) -> None:
    """The round that drops the overlay (a job's last, a worker's) gives the tile cache its
    state, so the finished job's image is read without reading a tile's state."""
    store, job_id, made = _fresh_job(servers, deltas, 2)
    merge_new(store, job_id, made[0])
    assert not store.fold(job_id).checkpointed
    merge_new(store, job_id, made[1])
    folded = store.fold(job_id, wait=True, checkpoint=True)
    assert folded.checkpointed and overlay_module.OVERLAYS.current(job_id) is None
    monkeypatch.setattr(store.tiles, "_read_state", [lambda **kw: pytest.fail("read a tile's state")] * (1 + SHARDS))
    _assert_same_state(store.state(store.get(job_id)), folded.state)


def test_readers_wait_for_a_round_in_place_and_a_failed_one_drops_the_overlay(deltas: tuple) -> None:
    """While a round adds to the overlay's state in place the job's readers wait, then read
    the round's overlay; a round that fails after it began leaves no overlay (its state
    would not match its batches), so the next read takes the tiles."""
    _, _, settings, r0 = deltas
    integrator = integrator_for(settings)
    overlays = overlay_module.Overlays()
    first = overlay_module.Overlay({0: 1}, frozenset(), integrator.start({"R0": r0}), None, {}, {}, {})
    overlays.put("job", first)
    read: list[State | None] = []
    reader = threading.Thread(target=lambda: read.append(overlays.state("job", {0: 1})))
    with overlays.merging("job", first, integrator) as state:
        assert state is first.state  # no one else holds it
        reader.start()
        time.sleep(0.3)
        assert not read  # waiting for the round
        state.passes += 1
        overlays.put("job", dataclasses.replace(first, batches=frozenset({"b"})))
    reader.join(10)
    assert read and read[0] is state and read[0].passes == 1
    del read[:], state, first  # nothing but the overlay refers to the state now
    with pytest.raises(RuntimeError):
        with overlays.merging("job", overlays.current("job"), integrator):
            raise RuntimeError("the round failed")
    assert overlays.current("job") is None and overlays.state("job", {0: 1}) is None


def test_a_round_writes_some_tiles_and_a_reader_without_the_overlay_sees_the_same_state(
        servers: list[EmbeddedRedis], deltas: tuple, monkeypatch: pytest.MonkeyPatch) -> None:
    """policy.checkpoint_tiles makes a round write a part of the tiles: the record counts a
    batch only once every tile has written it, the overlay goes on with what the others
    lack, and a process without the overlay (here: this one after dropping it) reads the
    same state from the tiles, their pending deltas and the accepted batches' counts."""
    store, job_id, made = _fresh_job(servers, deltas, 3)
    chosen: list[list[int]] = [[0, 2, 4], [1, 3]]  # the tiles each round writes
    monkeypatch.setattr(overlay_module.policy, "checkpoint_tiles", lambda *args: chosen.pop(0))
    merge_new(store, job_id, made[0])
    merge_new(store, job_id, made[1])
    folded = store.fold(job_id)
    assert folded is not None and not folded.checkpointed
    record = store.get(job_id)
    versions = _tile_versions(store, job_id)
    assert versions == [1, 0, 1, 0, 1, 0]
    assert record.folded_passes == 0 and store.r.hlen(keys.tofold(job_id)) == 2  # no batch on every tile yet
    overlay_module.OVERLAYS.drop(job_id)  # as a process that never folded the job
    _assert_same_state(store.state(record), folded.state)
    # The next round folds a third batch and writes tiles 1 and 3: the first two batches are
    # now on every tile but 5; the third on tiles 1 and 3 only.
    merge_new(store, job_id, made[2])
    folded = store.fold(job_id)
    assert folded is not None and not folded.checkpointed and store.r.hlen(keys.tofold(job_id)) == 3
    _assert_tiles_read_back(store, job_id, folded.state)
    monkeypatch.undo()
    assert_folded_once(store, job_id, made)


def test_a_round_stops_writing_tiles_when_the_next_round_is_due(
        servers: list[EmbeddedRedis], deltas: tuple, monkeypatch: pytest.MonkeyPatch) -> None:
    """A regular round writes the tiles policy.checkpoint_required asks for whatever the
    time, and the other tiles it chose only until the next round is due
    (policy.checkpoint_seconds; here at once): the rest keep their deltas pending, the
    overlay goes on with them, and a later round writes them. Each batch counts once, and
    the tiles read back the overlay's state."""
    store, job_id, made = _fresh_job(servers, deltas, 2)
    tiles = [4, 1, 5, 0, 3, 2]  # the order the round writes them in
    monkeypatch.setattr(overlay_module.policy, "checkpoint_tiles", lambda *args: list(tiles))
    monkeypatch.setattr(policy, "checkpoint_required", lambda order, *args: list(order)[:2])
    monkeypatch.setattr(policy, "checkpoint_seconds", lambda *args: 0.0)
    merge_new(store, job_id, made[0])
    folded = store.fold(job_id)
    assert folded is not None and not folded.checkpointed
    record = store.get(job_id)
    assert _tile_versions(store, job_id) == [0, 1, 0, 0, 1, 0]  # tiles 4 and 1 only
    assert record.folded_passes == 0 and store.r.hlen(keys.tofold(job_id)) == 1
    # The next round, with time to write, writes the tiles that lack a batch: all of them.
    monkeypatch.setattr(policy, "checkpoint_seconds", lambda *args: 60.0)
    merge_new(store, job_id, made[1])
    folded = store.fold(job_id)
    assert folded is not None and folded.checkpointed and _tile_versions(store, job_id) == [1, 2, 1, 1, 2, 1]
    _assert_tiles_read_back(store, job_id, folded.state)
    monkeypatch.undo()
    assert_folded_once(store, job_id, made)


def test_a_round_leaves_the_tiles_of_a_node_rewriting_its_file_for_later(
        servers: list[EmbeddedRedis], deltas: tuple, monkeypatch: pytest.MonkeyPatch) -> None:
    """A regular round writes no tile it may leave (beyond policy.checkpoint_required) to a
    node that is rewriting its append-only file (TiledState._rewriting, the node's INFO);
    the next round, the rewrite over, writes them. Each batch counts once."""
    store, job_id, made = _fresh_job(servers, deltas, 2)
    assert not any(store.tiles._rewriting(node) for node in range(len(store.tiles.nodes)))  # idle servers
    record = store.get(job_id)
    tiling = store.tiling(record)
    busy = tiling.node(0)
    monkeypatch.setattr(overlay_module.policy, "checkpoint_tiles", lambda *args: list(range(tiling.count)))
    monkeypatch.setattr(TiledState, "_rewriting", lambda self, node: node == busy)
    merge_new(store, job_id, made[0])
    assert store.fold(job_id) is not None

    def written() -> list[int]:
        return [k for k, version in enumerate(_tile_versions(store, job_id)) if version]

    assert written() == [k for k in range(tiling.count) if tiling.node(k) != busy]
    monkeypatch.setattr(TiledState, "_rewriting", lambda self, node: False)
    merge_new(store, job_id, made[1])
    folded = store.fold(job_id)
    assert folded is not None and folded.checkpointed and written() == list(range(tiling.count))
    monkeypatch.undo()
    assert_folded_once(store, job_id, made)


def test_no_write_starts_that_would_end_past_the_deadline(servers: list[EmbeddedRedis]) -> None:
    """TiledState._on_versions with a deadline: a transaction of TILES_PER_TRIP tiles that
    took 0.4 s, 0.6 s before the deadline, is not followed by another (it would end 0.2 s
    late); with no deadline every tile is written."""
    store = sharded_store([s.url for s in servers])
    tiles = {k: 0 for k in range(2 * state_module.TILES_PER_TRIP)}

    def slow(pipe: redis.client.Pipeline, k: int) -> None:
        time.sleep(0.4 / state_module.TILES_PER_TRIP)
        pipe.hset(keys.tile("deadline", k, "state"), "S", b"x")

    written = store.tiles._on_versions(0, "deadline", tiles, slow, time.time() + 0.6)
    assert written == list(range(state_module.TILES_PER_TRIP))
    assert store.tiles._on_versions(0, "deadline", tiles, slow) == list(tiles)


def _tile_versions(store: Jobs, job_id: str) -> list[int]:
    """Each tile's version (its checkpoints), on its node."""
    tiling = store.tiling(store.get(job_id))
    return [int(store.tiles.nodes[tiling.node(k)].hget(keys.tile(job_id, k, "meta"), "version") or 0)
            for k in range(tiling.count)]


def _assert_tiles_read_back(store: Jobs, job_id: str, state: State) -> None:
    """A process without the job's overlay (here: this one after dropping it) reads `state`
    from the tiles."""
    overlay_module.OVERLAYS.drop(job_id)
    _assert_same_state(store.state(store.get(job_id)), state)


def _assert_same_state(got: State, want: State) -> None:
    assert (got.passes, got.emitted, got.counters) == (want.passes, want.emitted, want.counters)
    for name, a in want.arrays().items():
        np.testing.assert_allclose(got.arrays()[name], a, rtol=1e-12, atol=0, err_msg=name)


def test_a_batch_is_told_the_passes_its_inputs_hold(servers: list[EmbeddedRedis], deltas: tuple) -> None:
    """GatherInputs.passes: the passes of the state the last fold round wrote the inputs
    from (a round in memory, a checkpoint, none yet), whatever was accepted since; a batch's
    first pass catches up the passes before it they lack (tests/test_progressive_stats.py)."""
    store, job_id, made = _fresh_job(servers, deltas, 3)
    assert store.batch_inputs(store.get(job_id)).passes == 0  # the set-up's inputs
    merge_new(store, job_id, made[0])
    assert store.batch_inputs(store.get(job_id)).passes == 0  # accepted, not yet folded
    store.fold(job_id)
    assert store.batch_inputs(store.get(job_id)).passes == made[0].n_passes
    merge_new(store, job_id, made[1])
    merge_new(store, job_id, made[2])
    store.fold(job_id, checkpoint=True)
    assert store.batch_inputs(store.get(job_id)).passes == sum(d.n_passes for d in made)


def test_a_state_holding_later_passes_alone_starts_batches_where_the_first_passes_would(
        servers: list[EmbeddedRedis], deltas: tuple) -> None:
    """The first round folds passes 2-3 before 0-1: the batch inputs' N is the state's
    scaled by the radius schedule over passes 0-1 against 2-3 (worker/stats.py,
    prefix_scale). The counter goes through the record: after a checkpoint, a round that
    restores the state from the tiles and adds passes 0-1 holds a prefix (no scale)."""
    store, job_id, made = _fresh_job(servers, deltas, 2)
    merge_new(store, job_id, made[1])
    store.fold(job_id)
    record = store.get(job_id)
    scale = stats.prefix_scale(record.settings.alpha, 2, made[1].counters)
    assert scale > 1.05
    N = store.state(record).N
    np.testing.assert_allclose(store.batch_inputs(record).count, N * scale, rtol=1e-6)
    store.fold(job_id, wait=True, checkpoint=True)
    merge_new(store, job_id, made[0])
    store.fold(job_id)
    record = store.get(job_id)
    state = store.state(record)
    assert state.passes == 4 and stats.prefix_scale(record.settings.alpha, 4, state.counters) == 1.0
    np.testing.assert_allclose(store.batch_inputs(record).count, state.N, rtol=1e-6)


def test_a_batch_reads_every_tiles_inputs_from_one_round(servers: list[EmbeddedRedis], deltas: tuple,
                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    """A round writes its inputs a tile at a time; a batch reading meanwhile would take some
    tiles' radius from it and the passes (its radius rule's catch-up) from tile 0's older
    round. It reads again until every tile is of one round, and takes them as they are once
    that fails INPUT_READS times (a folder killed mid-write: no hang)."""
    monkeypatch.setattr(state_module, "INPUT_RETRY_SECONDS", 0.02)
    store, job_id, made = _fresh_job(servers, deltas, 2)
    merge_new(store, job_id, made[0])
    store.fold(job_id)
    record = store.get(job_id)
    whole = store.batch_inputs(record)
    tiling = store.tiling(record)
    node, key = store.tiles.nodes[tiling.node(3)], keys.tile(job_id, 3, "inputs")
    this_round = node.get(key)
    other_round = dataclasses.replace(whole, radius=whole.radius * 0.5, passes=whole.passes + 5)
    node.set(key, encode_inputs(other_round, tiling.span(3)))
    threading.Timer(0.2, node.set, (key, this_round)).start()  # the round's write reaches tile 3
    read = store.batch_inputs(record)
    assert read.passes == whole.passes
    np.testing.assert_array_equal(read.radius, whole.radius)
    node.set(key, encode_inputs(other_round, tiling.span(3)))  # and stays torn
    started = time.monotonic()
    read = store.batch_inputs(record)
    assert time.monotonic() - started < 5.0
    assert read.passes == whole.passes  # tile 0's
    np.testing.assert_array_equal(read.radius[tiling.span(3)], other_round.radius[tiling.span(3)])


def test_a_worker_folds_only_for_passes_that_waited(servers: list[EmbeddedRedis], deltas: tuple,
                                                     tune: Callable[..., Config]) -> None:
    """Jobs.fold_if_stale, a worker's fold after its merge: only when accepted passes have
    waited for the image past the fold interval and fold_stale_seconds (not merely because
    the last round was long ago), and then as a checkpoint (a worker keeps no overlay)."""
    store, job_id, made = _fresh_job(servers, deltas, 3)
    merge_new(store, job_id, made[0])
    assert store.fold_if_stale(job_id) is None  # it has just been accepted
    tune(fold_stale_seconds=-1e6)  # any wait is too long
    folded = store.fold_if_stale(job_id)
    assert folded is not None and folded.checkpointed
    record = store.get(job_id)
    assert record.folded_passes == record.image_passes == record.passes == made[0].n_passes
    assert store.fold_if_stale(job_id) is None  # the image holds every accepted pass
    # The reducer folds the next batch in memory: its image holds it, so a worker does not fold.
    merge_new(store, job_id, made[1])
    assert not store.fold(job_id).checkpointed
    assert store.fold_if_stale(job_id) is None
    merge_new(store, job_id, made[2])
    assert store.fold_if_stale(job_id).checkpointed
    assert_folded_once(store, job_id, made)


def test_one_jobs_failing_round_does_not_stop_the_others(servers: list[EmbeddedRedis], deltas: tuple,
                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    """The reducer's folder (reducer.fold_owned): a round that raises something other than a
    Redis error (a bug, memory) is logged, the job's batches stay accepted for the next
    round, and the other jobs fold on."""
    from worker.reducer import fold_owned

    store, broken, made = _fresh_job(servers, deltas, 2)
    healthy = caustics_job(store, *deltas[1:])
    for job_id in (broken, healthy):
        merge_new(store, job_id, made[0])
    real = Jobs.fold_if_due

    def fold_if_due(self: Jobs, job_id: str, *args: object, **kwargs: object) -> object:
        if job_id == broken:
            raise ValueError("a bug in a round")
        return real(self, job_id, *args, **kwargs)

    monkeypatch.setattr(Jobs, "fold_if_due", fold_if_due)
    assert fold_owned(store, store.active_ids()) >= 1
    assert store.get(healthy).image_passes == made[0].n_passes
    assert store.get(broken).image_passes == 0 and store.get(broken).passes == made[0].n_passes
    monkeypatch.setattr(Jobs, "fold_if_due", real)
    fold_owned(store, store.active_ids())
    assert store.get(broken).image_passes == made[0].n_passes  # the next round took it


def test_the_batch_that_ends_a_job_hands_its_final_round_to_the_reducer(servers: list[EmbeddedRedis], deltas: tuple,
                                                                      tune: Callable[..., Config]) -> None:
    """The batch that spends the budget leaves the final round to the reducer, which
    holds the image in memory (one delta to add, then the checkpoint): its merge returns as
    soon as the folder has begun, and the job ends with every pass folded once. With no
    folder running, the worker ends the job itself after end_handoff_seconds."""
    from worker.reducer import fold_owned

    made = pickle.loads(deltas[0].read_bytes())[:3]
    store = sharded_store([s.url for s in servers])
    budget = sum(d.n_passes for d in made)
    # With the reducer: the merge does not wait out the hand-off.
    tune(end_handoff_seconds=60.0)
    job_id = caustics_job(store, *deltas[1:], max_passes=budget)
    stop = threading.Event()

    def folder() -> None:
        while not stop.wait(0.05):
            fold_owned(store, store.active_ids())

    thread = threading.Thread(target=folder, daemon=True)
    thread.start()
    try:
        for d in made[:-1]:
            merge_new(store, job_id, d)
        started = time.monotonic()
        merge_new(store, job_id, made[-1])
        assert time.monotonic() - started < 30.0
        while store.status(job_id) == Status.RUNNING and time.monotonic() - started < 60.0:
            time.sleep(0.05)
    finally:
        stop.set()
        thread.join()
    assert store.status(job_id) == Status.COMPLETED
    assert_folded_once(store, job_id, made)
    # Without: the worker ends it.
    tune(end_handoff_seconds=0.2)
    job_id = caustics_job(store, *deltas[1:], max_passes=budget)
    for d in made:
        merge_new(store, job_id, d)
    assert store.status(job_id) == Status.COMPLETED
    assert_folded_once(store, job_id, made)


def test_the_worker_leaves_the_final_round_to_a_folder_at_work(servers: list[EmbeddedRedis], deltas: tuple,
                                                               tune: Callable[..., Config]) -> None:
    """The reducer may be in a round of the job (its checkpoint writes) when the batch
    that ends the job is accepted. While a folder holds the job's fold lease, the worker
    does not begin the end itself after end_handoff_seconds (it would wait for the lease,
    then rebuild the state the folder holds in memory): the folder ends the job once its
    round is done, and every pass is folded once."""
    from worker.reducer import fold_owned
    from worker.store.fold_lease import FoldLease

    made = pickle.loads(deltas[0].read_bytes())[:2]
    store = sharded_store([s.url for s in servers])
    tune(end_handoff_seconds=0.3)
    job_id = caustics_job(store, *deltas[1:], max_passes=sum(d.n_passes for d in made))
    merge_new(store, job_id, made[0])
    held, done = threading.Event(), threading.Event()

    def reducer() -> None:
        with FoldLease(store.r, job_id, wait=True):  # a round of the job under way
            held.set()
            done.wait(30.0)
        while store.status(job_id) == Status.RUNNING:
            fold_owned(store, store.active_ids())
            time.sleep(0.05)

    folder = threading.Thread(target=reducer, daemon=True)
    folder.start()
    assert held.wait(10.0)
    merging = threading.Thread(target=merge_new, args=(store, job_id, made[1]), daemon=True)
    merging.start()
    try:
        time.sleep(1.5)  # five hand-off periods
        assert merging.is_alive()  # the merge waits for the hand-off
        assert not store.get(job_id).stopping  # and no process began the end: the folder at work keeps it
    finally:
        done.set()
    merging.join(60.0)
    folder.join(60.0)
    assert store.status(job_id) == Status.COMPLETED
    assert_folded_once(store, job_id, made)


def test_the_folder_wakes_for_a_jobs_ending_batch(servers: list[EmbeddedRedis], deltas: tuple,
                                                  tune: Callable[..., Config]) -> None:
    """The batch that ends a job is news (keys.FOLD_NEWS): a folder waiting on it
    (Jobs.wait_for_news, the reducer's folder thread) starts the final round at once, however
    long it would otherwise wait between looks (here 30 s), and the merge returns as soon
    as it has begun."""
    from worker.reducer import fold_owned

    made = pickle.loads(deltas[0].read_bytes())[:2]
    store = sharded_store([s.url for s in servers])
    store.r.delete(keys.FOLD_NEWS)
    tune(end_handoff_seconds=60.0)
    job_id = caustics_job(store, *deltas[1:], max_passes=sum(d.n_passes for d in made))
    merge_new(store, job_id, made[0])
    assert not store.r.exists(keys.FOLD_NEWS)  # a batch that does not end the job is no news
    stop = threading.Event()

    def folder() -> None:
        while not stop.is_set():
            store.wait_for_news(30.0)
            if not stop.is_set():
                fold_owned(store, store.active_ids())

    thread = threading.Thread(target=folder, daemon=True)
    thread.start()
    try:
        time.sleep(0.2)  # the folder waits on the news
        started = time.monotonic()
        merge_new(store, job_id, made[1])
        assert time.monotonic() - started < 10.0
        while store.status(job_id) == Status.RUNNING and time.monotonic() - started < 60.0:
            time.sleep(0.02)
        assert time.monotonic() - started < 10.0
    finally:
        stop.set()
        store.r.lpush(keys.FOLD_NEWS, "")  # wake the folder to stop
        thread.join()
    assert store.status(job_id) == Status.COMPLETED
    assert_folded_once(store, job_id, made)
