"""The adaptive sampler's counters (V_c, theta) go through the job store in a real Redis:
merged in any order, they sum exactly, and the store's state gives the image and the next
batch's inputs that an in-memory merge of the deltas as sent (float32 and float16 sums,
worker/store/tiles.py, as_sent) gives."""

from __future__ import annotations

import random
from dataclasses import replace

import numpy as np
import redis

from worker.engine import Engine
from worker.integrators.photon_mapping import GatherInputs
from worker.scene import bundled_scene_path, inline_meshes, load_scene_file
from worker.settings import Settings
from worker.store import Batch, Jobs, keys
from worker.store.tiles import as_sent


def test_counters_merge_through_the_store(redis_url: str) -> None:
    parsed, base = load_scene_file(bundled_scene_path("gap"))
    w, h = 24, 24
    settings = Settings(photons_per_pass=1 << 12, seed=8, resolution=(w, h), sampler="adaptive",
                        max_passes=1000)
    engine = Engine(parsed, base, settings)
    start = engine.start()
    inputs = engine.integrator.batch_inputs(start)
    assert isinstance(inputs, GatherInputs) and inputs.chains is not None
    deltas = [engine.run_batch(inputs, 2 * i, 2) for i in range(4)]
    store = Jobs(redis.Redis.from_url(redis_url))
    job_id = store.create(inline_meshes(parsed, base), settings, w, h, "gap")
    store.init_setup(store.get(job_id), {"R0": start.R0})
    tiling = store.tiling(store.get(job_id))
    memory = engine.integrator.start({"R0": start.R0})
    for d in deltas:
        engine.integrator.merge(memory, replace(d, sums=as_sent(d.sums, tiling, engine.integrator.sums.half)))
    store.r.hset(keys.job(job_id), mapping={"status": "running", "started": 1.0})
    for d in random.Random(3).sample(deltas, len(deltas)):
        assert store.merge(Batch(job_id, d.first_pass, d.n_passes), d, 0.1) == "merged"
    store.fold(job_id, wait=True, checkpoint=True)  # the accepted batches' deltas and counters into the state
    record = store.get(job_id)
    assert record.counters == memory.counters and memory.counters["splats"] > 0
    state = store.state(record)
    np.testing.assert_allclose(engine.integrator.image(state), engine.integrator.image(memory), rtol=1e-12,
                               atol=1e-300)
    assert store.batch_inputs(record).chains == engine.integrator.batch_inputs(memory).chains
