"""Stochastic spatial hashing against exact gathering, and reproducibility."""

from __future__ import annotations

import numpy as np
import pytest

from tests.conftest import render
from worker.integrators import photon_mapping_passes
from worker.integrators.base import Delta
from worker.integrators.photon_mapping import GatherInputs

SEEDS = range(40)


def test_stochastic_hash_is_unbiased_against_exact_gather(make_engine) -> None:
    """Same photons (same seed), two gathers: the per-seed difference has mean zero.

    Stochastic selection keeps one photon per table entry and scales it by the entry's
    count, so E[stochastic] = exact for both the flux sum S and the density D. Over 40
    seeds the mean difference of each quadrant's totals must lie within 4 standard errors
    (a 1-in-16000 event per check if unbiased), while single seeds differ clearly.
    """
    r = GatherInputs(np.full(32 * 32, 40.0))

    def quadrants(x: np.ndarray) -> np.ndarray:
        return x.reshape(2, 16, 2, 16, -1).sum(axis=(1, 3, 4)).ravel()

    diffs_S, diffs_D = [], []
    for seed in SEEDS:
        a, b = (make_engine("cornell-box", resolution=(32, 32), photons_per_pass=1 << 14, seed=seed,
                            gather=gather).run_batch(r, 0, 1) for gather in ("stochastic", "exact"))
        diffs_S.append(quadrants(a.S) - quadrants(b.S))
        diffs_D.append(quadrants(a.D[:, None]) - quadrants(b.D[:, None]))
        assert np.array_equal(a.Ld, b.Ld)  # the eye pass does not depend on the gather
    for diffs in (np.array(diffs_S), np.array(diffs_D)):
        se = diffs.std(axis=0, ddof=1) / np.sqrt(len(diffs))
        assert np.all(se > 0), "the two gathers never differed: the test would prove nothing"
        assert np.all(np.abs(diffs.mean(axis=0)) < 4.0 * se), (diffs.mean(axis=0), se)


def test_same_seed_gives_the_same_image_and_another_seed_does_not(make_engine) -> None:
    def run(seed: int) -> np.ndarray:
        eng = make_engine("cornell-caustics", resolution=(40, 30), photons_per_pass=1 << 14, seed=seed)
        return render(eng, 3).radiance()

    a, b, c = run(7), run(7), run(8)
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)


@pytest.mark.parametrize("radius", [10.0, 40.0])
def test_exact_gather_counts_each_photon_once_whatever_the_table_collisions(make_engine, monkeypatch,
                                                                             radius: float) -> None:
    """The exact grid's query visits each row of cells as one run of table entries
    (spatial_hash.cl, ball_rows). With a table of 16 entries for thousands of cells, a
    query's rows overlap one another in the table and run past its end nearly always;
    every photon within the radius must still count exactly once: the photon counts D equal
    bit for bit those of the full-sized table, the flux sums S within float summation order."""
    r = GatherInputs(np.full(32 * 32, radius))

    def batch() -> Delta:
        return make_engine("cornell-box", resolution=(32, 32), photons_per_pass=1 << 14, seed=3).run_batch(r, 0, 1)

    full = batch()
    monkeypatch.setattr(photon_mapping_passes, "_next_pow2", lambda n: 16)
    tiny = batch()
    assert full.D.sum() > 0.0
    assert np.array_equal(full.D, tiny.D)
    np.testing.assert_allclose(tiny.S, full.S, rtol=1e-5, atol=1e-6 * full.S.max())
