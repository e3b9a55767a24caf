"""Photon mapping, the host half: (stochastic) progressive photon mapping, SPPM and PPM.

Per pass: an eye pass makes one measurement point per pixel (SPPM jitters new points every
pass; PPM keeps pass 0's), photons are traced, and every point gathers the photons within
its radius. With `direct: nee` the eye pass also samples the lights at each point
(kernels/lights.cl) and photons store nothing at their first hit. A batch returns the
per-pixel sums below; the radius rule and the merge live in worker/stats.py, the error
estimate in worker/error_estimate.py. The device half is
worker/integrators/photon_mapping_passes.py. With `sampler: adaptive` the photons come from
Markov chains over photon paths (worker/adaptive.py, kernels/photon_chains.cl).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from kernels.contract import SumLayout
from worker import adaptive
from worker.error_estimate import ErrorEstimate, bias_estimate, estimate
from worker.integrators.base import Integrator
from worker.stats import Accumulators

# S: flux (rgb, smooth kernel, / k1 r^2); D: photon count / pi r^2; M: photons counted,
# each pass's at its own place in the radius schedule (kernels/spatial_hash.cl,
# shrink_radius: the merge adds alpha M to N, and the state does not keep M, BATCH_ONLY); Ld:
# directly seen emission (rgb); H: passes with a measurement point. Then the error estimator's sums
# (only for jobs that estimate their error): G the Laplacian, X1 and X2 the bias-corrected
# per-pass samples and their squares, L2 the squared per-pass Laplacians, Dh and Dh2 the
# per-pass change of the luminance estimate from radius r/2 to r and its square; with
# direct light by next-event estimation (`direct: nee`), Ld2 the squared luminance of each
# pass's Ld sample (its variance enters the error bound).
PHOTON_SUMS = (("S", 3), ("D", 1), ("M", 1), ("Ld", 3), ("H", 1))
BATCH_ONLY = ("M",)
# The photon sums are only added into the image and the radius rule: a batch sends them in
# half precision (worker/store/tiles.py). The error estimator's subtract one another
# (X2 - X1^2 / i, Dh2 - Dh^2 / i, ...) and go as float32.
HALF_SUMS = tuple(name for name, _ in PHOTON_SUMS)
ERROR_SUMS = (("G", 1), ("GR", 1), ("X1", 1), ("X2", 1), ("L2", 1), ("Dh", 1), ("Dh2", 1))
NEE_ERROR_SUMS = (("Ld2", 1),)


def sum_layout(error_estimation: bool, direct: str = "photons") -> SumLayout:
    errors = ERROR_SUMS + (NEE_ERROR_SUMS if direct == "nee" else ())
    return SumLayout(PHOTON_SUMS + (errors if error_estimation else ()), half=HALF_SUMS)


@dataclass(frozen=True)
class ChainInputs:
    """What a batch that runs chains reads from the merged counters: its frozen mutation
    size, its number of chains, the iterations a pass splits over them (None: photons per
    pass) and whether it is measuring (sampler auto before its choice: only its odd passes
    below adaptive.MEASURE_PASSES run chains, adaptive.runs_chains)."""

    theta: float
    chains: int
    iterations: int | None = None
    measuring: bool = False


@dataclass(frozen=True)
class GatherInputs:
    """What a batch of photon-mapping passes reads: the radius per pixel and the radius
    rule's count N there (zero if not given: the batch's first pass then shrinks the radius
    as a job's first pass does), the bias estimate its per-pass variance samples subtract
    (eq. 6.22; zero if not given), with the adaptive sampler its chains' inputs, and how
    many of the job's passes the state they come from holds (None: all those before the
    batch's first pass, as in a sequential render). A batch's pass k is the job's
    k-th in the radius rule whatever ran beside it: its first pass takes the rule also for
    the k - passes before it that the inputs lack (other batches' passes, rendering or not
    yet folded; kernels/spatial_hash.cl, shrink_radius), and its photons count for N at
    that step, so N is the sum of each pass's own count (sum M) in any grouping and order."""

    radius: np.ndarray
    bias: np.ndarray | None = None
    chains: ChainInputs | None = None
    count: np.ndarray | None = None
    passes: int | None = None


class PhotonMapping(Integrator[Accumulators]):
    """SPPM: a new jittered measurement point per pixel and pass (dissertation ch. 7)."""

    name = "sppm"
    fixed_points = False  # PPM: every pass uses pass 0's measurement points
    setup_arrays = ("R0",)
    inputs_type = GatherInputs

    @property
    def sums(self) -> SumLayout:
        return sum_layout(self.settings.error_estimation, self.settings.direct)

    @property
    def state_widths(self) -> dict[str, int]:
        return {"R0": 1, "N": 1, **{name: w for name, w in self.sums.widths if name not in BATCH_ONLY}}

    def start(self, setup: dict[str, np.ndarray]) -> Accumulators:
        return Accumulators.start(self.alpha, setup["R0"], self.sums, BATCH_ONLY)

    def restore(self, arrays: dict[str, np.ndarray], emitted: int, passes: int,
                counters: dict[str, int] | None = None) -> Accumulators:
        n = len(arrays["R0"])
        sums = {name: arrays[name] if name in arrays else self.sums.zeros(n, name)
                for name in self.sums.names if name not in BATCH_ONLY}
        return Accumulators(alpha=self.alpha, R0=arrays["R0"], N=arrays.get("N", np.zeros(n)),
                            sums=sums, emitted=emitted, passes=passes, counters=dict(counters or {}))

    def batch_inputs(self, state: Accumulators) -> GatherInputs:
        r, count = state.batch_start()
        bias = bias_estimate(r, state.G, state.emitted, self.settings.bias_constant) \
            if self.settings.error_estimation else None
        return GatherInputs(r, bias, self.chain_inputs(state.counters), count, state.passes)

    def chain_inputs(self, counters: dict[str, int]) -> ChainInputs | None:
        """A batch's chains: none with `sampler: uniform`, or with `auto` once it chose
        uniform tracing (adaptive.choice); measuring with `auto` before its choice."""
        sampler, photons = self.settings.sampler, self.settings.paths_per_pass
        measuring = False
        if sampler == "auto":
            choice = adaptive.choice(counters, photons)
            measuring = choice is None
            if choice is not None and not choice.chains:
                return None
        elif sampler != "adaptive":
            return None
        iterations = adaptive.iterations(photons)
        return ChainInputs(adaptive.theta(counters, self.settings.target_acceptance),
                           adaptive.chains(counters, iterations), iterations, measuring)

    def notes(self, counters: dict[str, int]) -> list[str]:
        """With `sampler: auto`, its choice and the figures it made it from (or that it is
        still measuring)."""
        if self.settings.sampler != "auto":
            return []
        choice = adaptive.choice(counters, self.settings.paths_per_pass)
        return [adaptive.measuring_note(counters) if choice is None else choice.note()]

    def merge_sums(self, state: Accumulators, sums: dict[str, np.ndarray],
                   pixels: slice = slice(None)) -> None:
        state.merge_sums(sums, pixels)

    def image(self, state: Accumulators) -> np.ndarray:
        return state.radiance()

    def estimate(self, state: Accumulators) -> ErrorEstimate | None:
        if not self.settings.error_estimation:
            return None
        return estimate(state, self.settings.confidence, self.settings.bias_constant,
                        discontinuities=self.settings.gather == "exact")


class ProgressivePhotonMapping(PhotonMapping):
    """PPM: one fixed set of measurement points (pass 0's), dissertation ch. 5."""

    name = "ppm"
    fixed_points = True
