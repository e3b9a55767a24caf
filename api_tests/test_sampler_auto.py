"""`sampler: auto` over real HTTP: a job's record says what the sampler chose and why."""

from __future__ import annotations

import pytest

from api_tests.cluster import Cluster, finished
from worker import adaptive
from worker.store import Jobs


@pytest.mark.parametrize("scene, chains", [("slit-room", True), ("cornell-box", False)])
def test_the_job_says_what_auto_chose_and_why(cluster: Cluster, scene: str, chains: bool) -> None:
    """A small job of the default sampler: once its measuring passes are merged, its view
    lists the choice (chains on slit-room, V_c ~ 1e-3; uniform photons on cornell-box) with
    the figures it was made from, those the job's merged counters give; while measuring,
    it says so."""
    photons = 1 << 15
    job = cluster.submit(scene_name=scene, settings={"max_passes": 24, "photons_per_pass": photons, "seed": 4,
                                                     "resolution": [32, 32]})
    assert job["settings"]["sampler"] == "auto"
    assert job["notes"] == [adaptive.measuring_note({})], job["notes"]
    done = cluster.wait(job["id"], finished, timeout=180.0)
    assert done["status"] == "completed", done
    jobs = Jobs(cluster.redis_client)
    record = jobs.get(job["id"])
    assert record is not None
    choice = adaptive.choice(record.counters, photons)
    assert choice is not None and choice.chains == chains, (choice, record.counters)
    assert done["notes"] == [choice.note()], done["notes"]
    said = "sampler auto: chains:" if chains else "sampler auto: uniform photons:"
    assert done["notes"][0].startswith(said) and f"V_c {choice.visible_fraction:.3g}" in done["notes"][0]
    measured = {name: value for name, value in record.counters.items() if name.startswith(adaptive.MEASURED)}
    half = adaptive.MEASURE_PASSES // 2
    assert measured[f"{adaptive.MEASURED}uniform_passes"] == measured[f"{adaptive.MEASURED}chain_passes"] == half
    # A batch starting now would follow the choice: chains in every pass, or none.
    chain_inputs = jobs.batch_inputs(record).chains
    assert (chain_inputs is not None and not chain_inputs.measuring) if chains else chain_inputs is None
