"""Progressive statistics: the per-pixel accumulators, the merge and the radius rule.

This is the one place the (S)PPM update lives. It uses the radius-free form of digest
section 11.2 (iii), which turns the dissertation's sequential update (eqs. 6.5-6.7,
7.2-7.5) into sums that commute, so batches from many workers can merge in any order:

    S += sum_p w * Phi_p / (pi r^2)    flux found at the radius r the pass used
    D += M / (pi r^2)                  photon density seen by the pixel
    E += photons emitted               (every path, also those that missed)
    N += alpha * pi * R^2 * dDb        R = the radius at merge time, dDb = the batch's
                                       sum of M / (pi r_b^2), r_b the radius it was given
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
gather at the radii a sequential run would use; its N increment is then alpha sum M =
alpha pi r_b^2 dDb, and with R = r_b (no other batch folded meanwhile) the merge leaves N
and R = sqrt(N / (pi D)) exactly where the sequential run would (N = pi R^2 D holds after
every pass). So the radius schedule does not depend on how passes are grouped into
batches, only on which batches share a fold round. S, D, E and
the emission sum are plain sums, so the estimate does not depend on merge order; N (and
so the future radius schedule) assumes locally uniform photon density when a batch was
gathered at a radius other than the current one, the same assumption PPM's flux
correction makes. All of it is float64 on the host.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from kernels.contract import SumLayout

if TYPE_CHECKING:
    from worker.integrators.base import Delta, State


def add_delta(state: "State", delta: "Delta") -> None:
    """The additive part of every merge: a batch's sums, photons, passes and counters."""
    for name in state.sums:
        state.sums[name] += delta.sums[name]
    state.emitted += delta.emitted
    state.passes += delta.n_passes
    for name, value in delta.counters.items():
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
    def start(cls, alpha: float, R0: np.ndarray, layout: SumLayout, batch_only: tuple[str, ...] = ()) -> "Accumulators":
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

    def merge(self, delta: "Delta") -> None:
        """Add a batch. Commutative in every sum; N uses the radius at merge time. A fold of
        several batches (`delta.steps`, each batch's D and Db in pass order) takes each
        batch's N increment at the radius the batches before it left, as merging them one
        at a time would: one increment at the round's first radius would shrink it less."""
        steps = delta.steps or [delta.sums]
        D = self.D if len(steps) == 1 else self.D.copy()  # the photon density as far as the steps went
        for i, step in enumerate(steps):
            r = self.radius() if i == 0 else radius(self.R0, self.N, D)
            dN = np.square(r)  # R^2 at merge time, then alpha pi R^2 dDb, in place
            dN *= self.alpha * math.pi
            dN *= step["Db"]
            self.N += dN
            if i + 1 < len(steps):
                D += step["D"]
        add_delta(self, delta)
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
