"""Stability where methods fail, where the expectation is crisp (bench/stability.py charts
the rest): alpha = 1 never shrinks the radius, an undersized stochastic hash adds noise but
no bias, and a long run does not drift."""

from __future__ import annotations

import numpy as np

from tests.analytic import FURNACE_L
from tests.conftest import render
from worker.integrators.photon_mapping import GatherInputs


def test_alpha_one_keeps_the_initial_radius(make_engine) -> None:
    """alpha = 1 is plain photon mapping at a fixed radius (dissertation 6.2): bias O(1)."""
    eng = make_engine("cornell-box", resolution=(24, 24), photons_per_pass=1 << 13, seed=1, alpha=1.0)
    st = render(eng, 8)
    # R0 as the device gathers at it (float32): N counts the photons found there.
    np.testing.assert_allclose(st.radius(), st.R0.astype(np.float32).astype(np.float64), rtol=1e-12)


def test_undersized_hash_table_adds_noise_not_bias(make_engine) -> None:
    """1/64 table entry per stored photon: photons of many cells crowd each entry, each still
    chosen uniformly and weighted by the count, so the mean over seeds matches the exact grid
    on the same photons while each pixel scatters more than with 4 entries per photon. At a
    small radius (R0/8), so that cells hold about one photon: the regime of Fig. 10.3 (with
    big cells the one-survivor-per-cell loss dwarfs any table size; bench/stability.py)."""
    r0 = make_engine("cornell-box", resolution=(32, 32), photons_per_pass=1 << 14, seed=0).start().R0
    r = GatherInputs(r0 / 8)
    scatter = {}
    for ratio in (1 / 64, 4.0):
        diffs = []
        for seed in range(20):
            kw = dict(resolution=(32, 32), photons_per_pass=1 << 14, seed=seed)
            hashed = make_engine("cornell-box", gather="stochastic", hash_entries_per_photon=ratio, **kw)
            exact = make_engine("cornell-box", gather="exact", **kw)
            diffs.append(hashed.run_batch(r, 0, 1).S.sum(axis=1) - exact.run_batch(r, 0, 1).S.sum(axis=1))
        d = np.array(diffs)  # (seeds, pixels)
        assert abs(d.mean()) < 4 * d.std(ddof=1) / np.sqrt(d.size), (ratio, d.mean(), d.std())
        scatter[ratio] = float(np.sqrt(np.mean(d ** 2)))
    assert scatter[1 / 64] > 2.0 * scatter[4.0], scatter


def test_long_run_does_not_drift(make_engine) -> None:
    """2000 passes on a tiny furnace: the float64 sums keep the mean on the analytic value
    and the error keeps falling (bench/stability.py runs 10^4 passes)."""
    eng = make_engine("furnace", resolution=(8, 8), photons_per_pass=1 << 10, seed=2)
    st = eng.start()
    rms = {}
    for k in range(2000):
        st.merge(eng.render_batch(st, k, 1))
        if k + 1 in (200, 2000):
            L = st.photon_radiance()[:, 0]
            rms[k + 1] = float(np.sqrt(np.mean((L / FURNACE_L - 1) ** 2)))
    assert abs(st.photon_radiance().mean() / FURNACE_L - 1) < 0.01
    assert rms[2000] < 0.6 * rms[200], rms
    assert np.all(np.isfinite(st.N)) and np.all(st.radius() > 0)
