"""Every settings field reaches the store, the worker's engine and the job view, unchanged."""

from __future__ import annotations

from pathlib import Path

import redis

from api_tests.cluster import Cluster
from worker.scene import bundled_scene_path, inline_meshes, load_scene_file
from worker.settings import DEFAULTS, Settings
from worker.store import Jobs
from worker.tasks import engine_for

# A value other than the default for every field.
CHANGED = {"method": "ppm", "gather": "stochastic", "direct": "nee", "sampler": "adaptive", "target_acceptance": 0.3,
           "alpha": 0.55, "photons_per_pass": 4096, "initial_radius": 0.3,
           "hash_entries_per_photon": 2.0, "seed": 99, "resolution": (24, 16), "error_estimation": True,
           "confidence": 0.8, "bias_constant": "dissertation", "max_passes": 3, "max_seconds": 50.0,
           "error_threshold": 0.02, "priority": "low", "max_bounces": 100}


def test_every_field_is_changed_by_the_fixture() -> None:
    assert set(CHANGED) == set(Settings.model_fields)
    for name, value in CHANGED.items():
        if name != "error_estimation":  # on by default, and needed by a threshold
            assert getattr(DEFAULTS, name) != value, name


def test_settings_reach_the_store_and_the_engine_whole(redis_url: str) -> None:
    jobs = Jobs(redis.Redis.from_url(redis_url))
    settings = Settings(**CHANGED)
    parsed, base = load_scene_file(bundled_scene_path("furnace"))
    job_id = jobs.create(inline_meshes(parsed, base), settings, 24, 16, "furnace")
    record = jobs.get(job_id)
    assert record.settings == settings
    engine = engine_for(jobs, record)
    assert engine.settings == settings
    assert engine.integrator.name == "ppm" and engine.integrator.settings is engine.settings
    assert (engine.arrays.width, engine.arrays.height) == (24, 16)
    assert engine.passes.setup()["R0"].max() == 0.3  # initial_radius


def test_settings_reach_the_job_view(tmp_path: Path) -> None:
    cluster = Cluster(tmp_path, workers=0)
    try:
        body = {**CHANGED, "resolution": list(CHANGED["resolution"])}
        job = cluster.submit(scene_name="furnace", settings=body)
        assert job["settings"] == {**body, "resolution": list(CHANGED["resolution"])}
        assert cluster.job(job["id"])["settings"] == job["settings"]
    finally:
        cluster.close()
