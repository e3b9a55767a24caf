"""Progressive statistics: the per-pixel accumulators, the merge and the radius rule.

This is the one place the (S)PPM update lives. It uses the radius-free form of digest
section 11.2 (iii), which turns the dissertation's sequential update (eqs. 6.5-6.7,
7.2-7.5) into sums that commute, so batches from many workers can merge in any order:

    S += sum_p w * Phi_p / (pi r^2)    flux found at the radius r the pass used
    D += M / (pi r^2)                  photon density seen by the pixel
    E += photons emitted               (every path, also those that missed)
    N += alpha * dM                    dM = the batch's photons, each pass's counted at its
                                       own place in the job's radius schedule (below)
    R^2 = N / (pi D)  (R0^2 while D = 0)
    L = S / E + (directly seen emission) / passes
    (adaptive photon tracing: each pass's sums are already in uniform photons, worker/adaptive.py)

S uses the smooth kernel K of eq. 6.34 (normalised by k1 r^2, so L estimates the same
radiance as with PPM's disc); D stays count based (pi r^2), as the radius rule derives
from counts. The error estimator's sums (worker/error_estimate.py) are additive too:
G (Laplacian of the luminance, /k1 r^2), X1 and X2 (sums of the bias-corrected per-pass
samples and of their squares), L2 (sum of the squared per-pass Laplacian estimates) and
H (passes with a measurement point). The layout of the sums is the integrator's
(worker/integrators/photon_mapping.py).

With r = R (a batch of one pass gathered at the current radius) this is exactly eq. 6.6:
R'^2 = R^2 (N + alpha M) / (N + M), and S/E equals tau/(pi R^2 E) of eq. 6.1. A batch of
several passes moves its radius on pass by pass on the device with the same rule
(shrink_radius, kernels/spatial_hash.cl), from the N and R it was given, so its passes
gather at the radii a sequential run would use, and its N increment is alpha times the
photons they found. A pass that stands for several of the job's passes (the batches
rendering beside it, and at a batch's first pass those its inputs lack) takes the rule
once for each, and its own photons count at its own step: after the passes its inputs
lack, and after those of the concurrent batches that start at an earlier pass. So N is a
plain sum too: the state does not depend on how passes are grouped into batches, nor on
which batches share a fold round, nor on merge order, and the radius follows the
sequential schedule (tests/test_progressive_stats.py). Not digest 11.2 (iii)'s rescaling
at the merge, which would shrink the radius twice for a batch whose device had already
counted the passes before it. The others' photons on the device are assumed
of the same density as the pass's own, the same assumption PPM's flux correction makes.
All of it is float64 on the host.

A state that holds passes out of the job's order (a later batch folded before an earlier
one) is not where the job's first `passes` passes would leave it: N / (pi D) averages
over the radii its passes used (eq. 6.6 keeps N / R^2 = sum M_k / R_k^2), and later
passes used smaller ones. Under a uniform density (the catch-up's assumption) eq. 6.6
gives N_k / M_k = k, so (R_k / R_0)^2 = a_k = prod_{i<k} (i + alpha) / (i + 1) whatever
the density, and N is proportional to the sum of a_k over the passes held. The batch
inputs (batch_start) scale N, and R^2 with it, by A(passes) / (sum of a_k held), with
A(K) = sum_{k<K} a_k = Gamma(K + alpha) / (Gamma(1 + alpha) Gamma(K)): 1 for the passes
0 .. passes-1, 1 / alpha for a state holding pass 1 alone (whose N / (pi D) is
alpha^2 R_0^2 where one pass leaves alpha R_0^2). The sum held is a counter (SCHEDULE)
each batch adds; without it a job whose first round folds pass 1 before pass 0 ends with
too small a radius. A batch
whose first pass comes before the passes its inputs hold (they were folded before it
started) goes back along the same schedule (rewind): pass 0 of a job whose first round
held pass 1 gathers at R_0 with N = 0, not at pass 1's radius.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from kernels.contract import SumLayout

if TYPE_CHECKING:
    from worker.integrators.base import Delta, State


SCHEDULE = "radius_schedule"  # counter: sum of a_k over the passes a state holds, in SCHEDULE_QUANTUM
# a_k <= 1, so a job's counter stays below 2^50 up to Settings' 10^7 passes at alpha = 1:
# exact through the record's Lua accounting (JSON numbers are doubles there) and HINCRBY.
SCHEDULE_QUANTUM = 2.0 ** -26
PREFIX_TOLERANCE = 1e-6  # relative: a scale this close to 1 is the quantum's rounding (the passes are 0 .. passes-1)
STIRLING_FROM = 64.0  # log_gamma_ratio's series: its first omitted term is below 1e-16 from here


def log_gamma_ratio(x: float, alpha: float) -> float:
    """log Gamma(x + alpha) - log Gamma(x) for x >= 1, 0 <= alpha <= 1, to about 1e-15
    absolute (math.lgamma's difference loses eps * x log x): Stirling's series in the form
    (x - 1/2) log1p(alpha / x) + alpha log(x + alpha) - alpha + ..., from x + shift >= 64."""
    shift = 0.0
    while x + shift < STIRLING_FROM:  # Gamma(z + 1) = z Gamma(z)
        shift += 1.0
    z = x + shift
    out = (z - 0.5) * math.log1p(alpha / z) + alpha * math.log(z + alpha) - alpha
    for power, divisor in ((1, 12.0), (3, -360.0), (5, 1260.0), (7, -1680.0)):
        out += (1.0 / (z + alpha) ** power - 1.0 / z ** power) / divisor
    return out - sum(math.log1p(alpha / (x + i)) for i in range(int(shift)))


def _log_schedule_sum(alpha: float, passes: int) -> float:
    """log A(passes), A(K) = sum_{k<K} a_k (passes > 0)."""
    return log_gamma_ratio(passes, alpha) - math.lgamma(1.0 + alpha)


def schedule_count(alpha: float, first: int, n: int) -> int:
    """A batch's SCHEDULE counter: sum of a_k over passes first .. first+n-1."""
    upper = _log_schedule_sum(alpha, first + n)
    part = math.exp(upper) * (-math.expm1(_log_schedule_sum(alpha, first) - upper) if first > 0 else 1.0)
    return round(part / SCHEDULE_QUANTUM)


def prefix_scale(alpha: float, passes: int, counters: dict[str, int]) -> float:
    """How much N (and R^2) of a state holding `passes` passes is below the job's first
    `passes` passes' (>= 1; 1 for a state of no SCHEDULE counter, as before it)."""
    held = counters.get(SCHEDULE, 0)
    if passes <= 0 or held <= 0:
        return 1.0
    scale = math.exp(_log_schedule_sum(alpha, passes)) / (held * SCHEDULE_QUANTUM)
    return 1.0 if scale < 1.0 + PREFIX_TOLERANCE else scale


def rewind(alpha: float, passes: int, first: int) -> tuple[float, float]:
    """The factors on N and on R^2 (and the bias) that take the job's first `passes` passes'
    radius back to its first `first` passes' (first < passes: a batch whose inputs' state
    already holds later passes, folded before it started), under the uniform density of
    prefix_scale: N_k = N_P A(k) / A(P), R_k^2 = R_P^2 a_k / a_P, a_k = A(k) alpha / k
    (a_0 = 1, N_0 = 0)."""
    if first >= passes:
        return 1.0, 1.0
    log_p = _log_schedule_sum(alpha, passes)
    a_p = math.exp(log_p) * alpha / passes
    if first == 0:
        return 0.0, 1.0 / a_p
    ratio = math.exp(_log_schedule_sum(alpha, first) - log_p)
    return ratio, ratio * passes / first


def add_sums(state: State, sums: dict[str, np.ndarray], pixels: slice = slice(None)) -> None:
    """The per-pixel additive part of every merge, over a run of pixels: each sum the state
    keeps adds its part (a float32 delta's adds in the state's float64, exactly converted);
    a sum the parts lack adds nothing there."""
    for name, part in sums.items():
        if name in state.sums:
            state.sums[name][pixels] += part


def add_counts(state: State, n_passes: int, emitted: int, counters: dict[str, int]) -> None:
    """The scalar additive part of every merge: passes, photons and counters."""
    state.emitted += emitted
    state.passes += n_passes
    for name, value in counters.items():
        state.counters[name] = state.counters.get(name, 0) + value


def radius(R0: np.ndarray, N: np.ndarray, D: np.ndarray) -> np.ndarray:
    """Current radius per pixel: R^2 = N / (pi D) where photons were ever found.

    A pixel that never found a photon (D = 0) carries no statistics, so its radius is
    free (the dissertation only asks R0 > 0): it takes R0 capped at the largest radius
    of the lit pixels. That keeps the stochastic hash's cell (twice the largest current
    radius, dissertation 10.2.2) shrinking with the radii instead of staying at 2 R0
    because of pixels no light reaches.
    """
    lit = D > 0.0
    r2 = R0 ** 2
    if lit.any():  # in place: a frame's temporaries cost more than the arithmetic
        lit_r2 = math.pi * D
        with np.errstate(divide="ignore", invalid="ignore"):  # unlit pixels' quotients are not used
            np.divide(N, lit_r2, out=lit_r2)
        np.minimum(r2, np.max(lit_r2, where=lit, initial=-np.inf), out=r2)
        np.copyto(r2, lit_r2, where=lit)
    return np.sqrt(r2, out=r2)


@dataclass
class Accumulators:
    """A photon-mapping job's shared per-pixel state (float64)."""

    alpha: float
    R0: np.ndarray  # (pixels,) initial radius
    N: np.ndarray
    sums: dict[str, np.ndarray]  # every name of the integrator's SumLayout
    emitted: int = 0
    passes: int = 0
    counters: dict[str, int] = field(default_factory=dict)  # summed scalars (Delta.counters)
    # radius() as of the last merge: a batch's inputs, its merge and the error estimate all
    # ask for it, and at a megapixel each computation costs as much as the merge's sums.
    _radius: np.ndarray | None = field(default=None, repr=False, compare=False)

    @classmethod
    def start(cls, alpha: float, R0: np.ndarray, layout: SumLayout, batch_only: tuple[str, ...] = ()) -> Accumulators:
        """Empty state: no pass merged, every radius at its initial value; it keeps every sum
        of `layout` but those only a batch carries (`batch_only`)."""
        if not 0.0 < alpha <= 1.0:
            raise ValueError("alpha must lie in (0, 1]")
        n = len(R0)
        return cls(alpha=alpha, R0=np.asarray(R0, np.float64), N=np.zeros(n),
                   sums={name: layout.zeros(n, name) for name in layout.names if name not in batch_only})

    def __getattr__(self, name: str) -> np.ndarray:
        sums = self.__dict__.get("sums")  # (no recursion while unpickling, before `sums` exists)
        if sums is not None and name in sums:
            return sums[name]
        raise AttributeError(name)

    def arrays(self) -> dict[str, np.ndarray]:
        return {"R0": self.R0, "N": self.N, **self.sums}

    def radius(self) -> np.ndarray:
        """The current radius per pixel (read-only: computed once per merge)."""
        if self._radius is None:
            self._radius = radius(self.R0, self.N, self.D)
            self._radius.flags.writeable = False
        return self._radius

    def batch_start(self) -> tuple[np.ndarray, np.ndarray]:
        """The radius and N a batch starts from: the job's first `passes` passes' (the state's
        own when it holds those; else scaled by prefix_scale)."""
        scale = prefix_scale(self.alpha, self.passes, self.counters)
        if scale == 1.0:
            return self.radius(), self.N
        N = self.N * scale
        return radius(self.R0, N, self.D), N

    def merge(self, delta: Delta) -> None:
        """Add a batch (or a fold round's batches at once): every sum adds, and N takes alpha
        times the photons the passes counted at their own places in the radius schedule
        (M, kernels/spatial_hash.cl). Commutative: the same state whatever the order and
        grouping of the batches."""
        self.merge_sums(delta.sums)
        add_counts(self, delta.n_passes, delta.emitted, delta.counters)

    def merge_sums(self, sums: dict[str, np.ndarray], pixels: slice = slice(None)) -> None:
        """The per-pixel part of `merge` over a run of pixels (a tile of a fold round)."""
        if "M" in sums:
            self.N[pixels] += self.alpha * np.asarray(sums["M"], np.float64)
        add_sums(self, sums, pixels)
        self._radius = None

    def photon_radiance(self, pixels: slice = slice(None)) -> np.ndarray:
        """The density estimate S/E alone, (pixels, 3), of all pixels or a run of them."""
        S = self.S[pixels]
        return S / self.emitted if self.emitted > 0 else np.zeros_like(S)

    def radiance(self) -> np.ndarray:
        """Current estimate L = S/E + Ld/passes, (pixels, 3) float64."""
        if self.passes == 0:
            return np.zeros_like(self.S)
        return self.photon_radiance() + self.Ld / self.passes
