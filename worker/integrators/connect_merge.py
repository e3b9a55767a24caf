"""Vertex connection and merging, the host half: the hybrid integrator `vcm` and its
unbiased and light-tracing modes `bpt` and `lt` (Georgiev et al. 2012, Hachisuka et al.
2012, dissertation ch. 9; equations in kernels/vcm_*.cl).

Per pass: `photons_per_pass` light subpaths are traced, their non-specular vertices stored
and each connected to the camera (light tracing: a splat to any pixel); then one camera
subpath per pixel, at every non-specular vertex, samples a light, connects to the vertices
of one light subpath and (vcm) merges with the light vertices within the pass's radius,
all weighted by the balance heuristic in which merging's pdf carries pi r^2 N_L.

The radius depends only on the global pass index and R0, r_k^2 = R0^2 (k + 1)^(alpha - 1),
so every pass is an independent per-pixel sample and batches from any number of workers
merge by plain addition in any order. R0 is the job's setup array, computed as SPPM's
(worker/integrators/photon_mapping_passes.py: light vertices, which are photons, per pass).

Sums per pixel: C the radiance of every pass; for the error estimate Y2 the squared
luminance of each pass's sample, H the passes whose camera ray hit a surface, and (vcm) Mh,
Mh2 the change of the merged estimate from radius r/2 to r and its square. The device half
is worker/integrators/connect_merge_passes.py.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from kernels.contract import LUMINANCE, SumLayout
from worker.error_estimate import EDGE_FACTOR, EDGE_MARGIN, FLOOR_FRACTION, ErrorEstimate, image_average, student_t
from worker.integrators.base import Integrator
from worker.stats import add_sums


@dataclass
class HybridState:
    """A hybrid job's progressive state: R0 and the per-pixel sums (float64)."""

    R0: np.ndarray
    sums: dict[str, np.ndarray]
    emitted: int = 0
    passes: int = 0
    counters: dict[str, int] = field(default_factory=dict)  # none of its own; summed like `emitted`

    def __getattr__(self, name: str) -> np.ndarray:
        sums = self.__dict__.get("sums")
        if sums is not None and name in sums:
            return sums[name]
        raise AttributeError(name)

    def arrays(self) -> dict[str, np.ndarray]:
        return {"R0": self.R0, **self.sums}


@dataclass(frozen=True)
class HybridInputs:
    """What a batch of hybrid passes reads: R0 (one value for the image); the merging
    radius of every pass follows from it and the pass index (`pass_radius`)."""

    r0: float


def pass_radius(r0: float, alpha: float, pass_index: int) -> float:
    """The merging radius of global pass k: r_k^2 = R0^2 (k + 1)^(alpha - 1)."""
    return r0 * (pass_index + 1) ** (0.5 * (alpha - 1.0))


class ConnectMerge(Integrator[HybridState]):
    """VCM: light tracing, next-event estimation, connections and merging."""

    name = "vcm"
    program = "hybrid"
    connects = True  # vertex connection: NEE, subpath connections (and light tracing, always on)
    merges = True  # vertex merging: the density estimate
    setup_arrays = ("R0",)
    inputs_type = HybridInputs

    @property
    def sums(self) -> SumLayout:
        errors = (("Y2", 1), ("H", 1)) + ((("Mh", 1), ("Mh2", 1)) if self.merges else ())
        if not self.settings.error_estimation:
            return SumLayout((("C", 3),), half=("C",))
        # C is also the mean the variance subtracts (Y2 - i lum^2): float32 in a delta then.
        return SumLayout((("C", 3),) + errors, half=("H",))

    @property
    def state_widths(self) -> dict[str, int]:
        return {"R0": 1, **dict(self.sums.widths)}

    def start(self, setup: dict[str, np.ndarray]) -> HybridState:
        r0 = np.asarray(setup["R0"], np.float64)
        return HybridState(R0=r0, sums={name: self.sums.zeros(len(r0), name) for name in self.sums.names})

    def restore(self, arrays: dict[str, np.ndarray], emitted: int, passes: int,
                counters: dict[str, int] | None = None) -> HybridState:
        n = len(arrays["R0"])
        sums = {name: arrays[name] if name in arrays else self.sums.zeros(n, name) for name in self.sums.names}
        return HybridState(R0=arrays["R0"], sums=sums, emitted=emitted, passes=passes,
                           counters=dict(counters or {}))

    def batch_inputs(self, state: HybridState) -> HybridInputs:
        return HybridInputs(float(state.R0[0]))

    def merge_sums(self, state: HybridState, sums: dict[str, np.ndarray],
                   pixels: slice = slice(None)) -> None:
        add_sums(state, sums, pixels)

    def image(self, state: HybridState) -> np.ndarray:
        return state.C / state.passes if state.passes else np.zeros_like(state.C)

    def estimate(self, state: HybridState) -> ErrorEstimate | None:
        if not self.settings.error_estimation:
            return None
        return hybrid_estimate(state, self.settings.confidence)


class BidirectionalPathTracing(ConnectMerge):
    """BPT: connections only (unbiased)."""

    name = "bpt"
    merges = False


class LightTracing(ConnectMerge):
    """Light tracing: splats to the camera, plus emission the camera sees directly or
    through specular surfaces (no other technique samples those paths)."""

    name = "lt"
    connects = False
    merges = False


def hybrid_estimate(state: HybridState, confidence: float) -> ErrorEstimate:
    """The per-pixel error bound of a hybrid job (the rules of worker/error_estimate.py):

    noise  = t(confidence, i - 1) sqrt(V / i), V the sample variance of the per-pass
             luminance samples (independent across passes, whatever their radii);
    bias   = EDGE_FACTOR x the mean change dh of the merged part from radius r/2 to r
             (3/4 of the bias where the density is smooth, 1/2 where it has an edge in the
             disc: the factor covers both), counted beyond EDGE_MARGIN standard errors (as the
             discontinuity bias of SPPM: the change rests on few vertices, so it is noisy);
    never-lit pixels (a camera ray hit something, but no non-zero sample yet): the one-sided
             Poisson bound on the rate of a non-zero sample, -ln(1 - c) / i, times the RMS
             per-pass sample of the median lit pixel. Pixels whose camera rays never hit anything
             (background) are not measured.
    """
    i = state.passes
    n = len(state.C)
    lum = state.C @ LUMINANCE / max(i, 1)
    measured = state.H > 0.0
    known = measured & (state.Y2 > 0.0)
    dark = measured & ~known
    bias = np.zeros(n)
    if i >= 2:
        t = student_t(confidence, i - 1)
        var = np.maximum(state.Y2 - i * lum ** 2, 0.0) / (i - 1)
        noise = t * np.sqrt(var / i)
        significant = np.zeros(n)
        if "Mh" in state.sums:
            dh = state.Mh / i
            dh_se = np.sqrt(np.maximum(state.Mh2 - i * dh ** 2, 0.0) / (i - 1) / i)
            z = student_t(math.erf(EDGE_MARGIN / math.sqrt(2.0)), i - 1)
            bias = EDGE_FACTOR * dh
            significant = EDGE_FACTOR * np.maximum(np.abs(dh) - z * dh_se, 0.0)
        rms = float(np.median(np.sqrt(state.Y2[known] / i))) if known.any() else math.inf
        noise = np.where(dark, rms * -math.log1p(-confidence) / i, noise)
        bound = noise + significant
    else:
        noise = bound = np.full(n, np.inf)
    lit = measured & (lum > 0.0)
    floor = FLOOR_FRACTION * float(lum[lit].mean()) if lit.any() else 1.0
    weight = np.maximum(lum, floor)
    with np.errstate(invalid="ignore", divide="ignore"):
        relative = np.where(measured & np.isfinite(bound), bound / weight, 1.0)
    relative[dark] = np.minimum(relative[dark], 1.0)
    average = image_average(relative, weight, known, measured) if i >= 2 else 1.0
    return ErrorEstimate(luminance=lum, bias=bias, noise=noise, bound=bound, relative=relative,
                         measured=measured, known=known, average=average, confidence=confidence)
