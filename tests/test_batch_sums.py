"""Who owns a batch's sums (worker/engine.py, Device.read_sums): they are views of the
device's sums buffer mapped into host memory, with no copy, and stay valid for as long as
anything references them, whatever the engine runs next; once nothing does, the next
batch sums into the same memory again."""

from __future__ import annotations

import numpy as np

from worker.integrators.photon_mapping import GatherInputs

RES = (48, 32)
PHOTONS = 1 << 12


def _copies(sums: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    return {name: np.array(a) for name, a in sums.items()}


def test_kept_sums_survive_later_batches_and_setup(make_engine):
    eng = make_engine("cornell-caustics", RES, photons_per_pass=PHOTONS)
    r = GatherInputs(eng.start().radius())
    first = eng.run_batch(r, 0, 1)
    kept = _copies(first.sums)
    second = eng.run_batch(r, 1, 2)
    eng.passes.setup()  # an eye pass and a probe gather that write the device's sums
    third = eng.run_batch(r, 3, 1)
    for name in kept:
        assert np.array_equal(first.sums[name], kept[name]), name
    assert not np.array_equal(second.S, first.S)  # (the batches differ, so a clobbered delta would show)
    assert not np.array_equal(third.S, first.S)
    assert second.H.max() == 2.0 and first.H.max() == 1.0


def test_dropped_sums_are_summed_into_again(make_engine):
    eng = make_engine("cornell-caustics", RES, photons_per_pass=PHOTONS)
    r = GatherInputs(eng.start().radius())
    delta = eng.run_batch(r, 0, 1)
    address = delta.S.ctypes.data
    del delta
    again = eng.run_batch(r, 1, 1)
    assert again.S.ctypes.data == address  # the same memory: no new buffer, no copy
    fresh = make_engine("cornell-caustics", RES, photons_per_pass=PHOTONS).run_batch(r, 1, 1)
    for name in fresh.sums:  # and nothing of the batch before is left in it
        assert np.array_equal(again.sums[name], fresh.sums[name]), name
