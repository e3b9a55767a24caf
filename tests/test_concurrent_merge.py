"""The same batches merged by several concurrent worker processes, each in its own
shuffled order, against a real Redis: every batch counts exactly once and the state is
the same whatever the order (S, D, Ld and E are sums; N only schedules future radii): the
sum of the deltas as sent (worker/store/tiles.py, as_sent)."""

from __future__ import annotations

import multiprocessing as mp
import pickle
import random
from pathlib import Path

import numpy as np
import redis

from tests.helpers import running_job
from worker.engine import Engine
from worker.integrators.base import Delta
from worker.integrators.photon_mapping import GatherInputs
from worker.scene import bundled_scene_path, inline_meshes, load_scene_file
from worker.settings import Settings
from worker.store import Batch, Jobs
from worker.store.tiles import as_sent

BATCHES = 12
PROCESSES = 4


def _merge_all(url: str, job_id: str, deltas_file: str, order_seed: int) -> list[str]:
    deltas: list[Delta] = pickle.loads(Path(deltas_file).read_bytes())
    store = Jobs(redis.Redis.from_url(url))
    order = list(range(len(deltas)))
    random.Random(order_seed).shuffle(order)
    return [store.merge(Batch(job_id, deltas[i].first_pass, deltas[i].n_passes), deltas[i], 0.1) for i in order]


def test_concurrent_shuffled_merges_give_one_state(redis_url: str, tmp_path: Path) -> None:
    parsed, base = load_scene_file(bundled_scene_path("cornell-caustics"))
    w, h = 64, 48
    settings = Settings(photons_per_pass=1 << 14, seed=21, resolution=(w, h))
    engine = Engine(parsed, base, settings)
    r0 = engine.start().R0
    deltas = [engine.run_batch(GatherInputs(r0 * (1.0 - 0.03 * i)), 2 * i, 2) for i in range(BATCHES)]
    deltas_file = tmp_path / "deltas.pkl"
    deltas_file.write_bytes(pickle.dumps(deltas))
    store = Jobs(redis.Redis.from_url(redis_url))
    scene = inline_meshes(parsed, base)
    states = []
    for trial in range(2):
        unlimited = settings.model_copy(update={"max_passes": 1000, "max_seconds": None})
        job_id = running_job(store, w, h, r0, unlimited, scene, "cornell-caustics")
        with mp.get_context("spawn").Pool(PROCESSES) as pool:
            outcomes = pool.starmap(_merge_all, [(redis_url, job_id, str(deltas_file), 100 * trial + p)
                                                  for p in range(PROCESSES)])
        flat = [o for per_process in outcomes for o in per_process]
        assert flat.count("merged") == BATCHES and flat.count("duplicate") == (PROCESSES - 1) * BATCHES
        record = store.get(job_id)
        assert record.passes == 2 * BATCHES
        assert record.emitted == sum(d.emitted for d in deltas)
        store.fold(job_id, wait=True, checkpoint=True)  # the reducer's round
        states.append(store.state(record))
    a, b = states
    tiling, half = store.tiling(record), record.integrator.sums.half
    sent = [as_sent(d.sums, tiling, half) for d in deltas]
    for name in a.sums:  # rounding of a reordered sum scales with its largest term
        expected = sum(d[name] for d in sent)
        atol = 1e-12 * np.abs(expected).max()
        np.testing.assert_allclose(getattr(a, name), expected, rtol=1e-12, atol=atol)
        np.testing.assert_allclose(getattr(b, name), getattr(a, name), rtol=1e-12, atol=atol)
    np.testing.assert_allclose(a.radiance(), b.radiance(), rtol=1e-12, atol=1e-300)
    lit = a.D > 0
    assert abs(np.mean(a.radius()[lit] ** 2) / np.mean(b.radius()[lit] ** 2) - 1) < 0.03
