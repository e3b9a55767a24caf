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
from scipy import ndimage, special
from scipy import stats as scipy_stats

from kernels.contract import LUMINANCE, SumLayout
from worker.error_estimate import FLOOR_FRACTION, ErrorEstimate, folded_quantile, image_average, student_t
from worker.integrators.base import Integrator
from worker.stats import add_sums

NEIGHBOURHOOD = 3  # pixels a side of the window whose changes dh test a pixel's density for an edge
EDGE_DETECTION = 0.05  # the test's level (smooth pixels taken for rough: more where dh is heavy-tailed, few passes)
REMAINDER = 1.0 / math.sqrt(3.0)  # RMS per unit of dh of the r/2 estimate's bias where the density is rough


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
        if self.settings.resolution is None:
            raise ValueError("settings not yet given a frame (Settings.for_frame)")
        return hybrid_estimate(state, self.settings.confidence, self.settings.resolution[0])


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


def rough_pixels(dh: np.ndarray, dh_se: np.ndarray, passes: int, width: int) -> np.ndarray:
    """The pixels whose neighbourhood (NEIGHBOURHOOD x NEIGHBOURHOOD pixels, cut at the
    frame's border) contradicts a smooth density: the change dh of the merged part from r/2
    to r is zero in expectation where the density is constant in the disc, so under that
    hypothesis each pixel's (dh / s_dh)^2, its t statistic with passes - 1 degrees of freedom
    taken to the normal score of the same tail, is chi-squared with 1 degree of freedom, and
    their sum over the n pixels with a standard error is chi-squared with n; a sum beyond
    its 1 - EDGE_DETECTION quantile marks the pixel rough. Pooling finds the edges that one
    pixel's few merged vertices cannot: an edge runs through its neighbours too, and their
    noises are independent."""
    height = len(dh) // width
    has = dh_se > 0.0
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(has, np.abs(dh) / dh_se, 0.0)
    window = np.ones((NEIGHBOURHOOD, NEIGHBOURHOOD))
    count = np.rint(ndimage.convolve(has.astype(np.float64).reshape(height, width), window, mode="constant")).ravel()
    critical = scipy_stats.chi2.isf(EDGE_DETECTION, np.arange(NEIGHBOURHOOD ** 2 + 1))[count.astype(np.intp)]
    # A normal score is below its t (t's tails are heavier): windows whose t^2 sum stays under
    # the quantile are smooth, and only the others' pixels need the (costly) t distribution.
    score = t ** 2
    candidate = ndimage.convolve(score.reshape(height, width), window, mode="constant").ravel() > critical
    exact = has & ndimage.binary_dilation(candidate.reshape(height, width), window.astype(bool)).ravel()
    score[exact] = special.ndtri(special.stdtr(passes - 1, -t[exact])) ** 2
    total = ndimage.convolve(score.reshape(height, width), window, mode="constant").ravel()
    return candidate & (count > 0) & (total > critical)


def hybrid_estimate(state: HybridState, confidence: float, width: int) -> ErrorEstimate:
    """The per-pixel error bound of a hybrid job (the rules of worker/error_estimate.py), its
    frame `width` pixels wide:

    noise  = t(confidence, i - 1) sqrt(V / i), V the sample variance of the per-pass
             luminance samples (independent across passes, whatever their radii);
    bias   = (vcm) dh, the mean change of the merged part from radius r/2 to r over the
             passes, each at its own radius (so it is the mean of the passes' changes, as
             the image is the mean of their samples). The error is the noise plus E[dh] +
             b', b' the bias of the estimate at r/2: between 0 (an edge beyond r/2
             in the disc: all the bias is in dh) and dh (a bias linear in r: an edge
             through the disc). It is taken as a zero-mean error with the RMS of a value
             uniform between those, REMAINDER |dh| = |dh| / sqrt(3) (zero-mean: an edge
             pixel's edge lies beyond r/2 more often than not). So where the density is
             rough (`rough_pixels`) the bound is the `confidence` quantile of |dh + sigma T| (`folded_quantile`),
             sigma^2 = V / i + s_dh^2 + (REMAINDER dh)^2, the three errors taken as
             independent; elsewhere it is the noise (a smooth density's bias is too small to
             tell from dh's noise, and adding that noise would over-cover);
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
        var = np.maximum(state.Y2 - i * lum ** 2, 0.0) / (i - 1)
        noise = student_t(confidence, i - 1) * np.sqrt(var / i)
        bound = noise.copy()
        if "Mh" in state.sums:
            bias = state.Mh / i
            dh_var = np.maximum(state.Mh2 - i * bias ** 2, 0.0) / (i - 1) / i
            rough = rough_pixels(bias, np.sqrt(dh_var), i, width)
            sigma = np.sqrt(var[rough] / i + dh_var[rough] + (REMAINDER * bias[rough]) ** 2)
            bound[rough] = folded_quantile(bias[rough], sigma, confidence, i - 1)
        rms = float(np.median(np.sqrt(state.Y2[known] / i))) if known.any() else math.inf
        noise = np.where(dark, rms * -math.log1p(-confidence) / i, noise)
        bound = np.where(dark, noise, bound)
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
