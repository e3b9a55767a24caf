"""Progressive statistics: the per-pixel accumulators, the merge and the radius rule.

This is the one place the (S)PPM update lives. It uses the radius-free form of digest
section 11.2 (iii), which turns the dissertation's sequential update (eqs. 6.5-6.7,
7.2-7.5) into sums that commute, so batches from many workers can merge in any order:

    S += sum_p w * Phi_p / (pi r^2)    flux found at the radius r the pass used
    D += M / (pi r^2)                  photon density seen by the pixel
    E += photons emitted               (every path, also those that missed)
    N += alpha * pi * R^2 * dD         R = the radius at merge time
    R^2 = N / (pi D)  (R0^2 while D = 0)
    L = S / E + (directly seen emission) / passes

With r = R (a batch of one pass gathered at the current radius) this is exactly eq. 6.6:
R'^2 = R^2 (N + alpha M) / (N + M), and S/E equals tau/(pi R^2 E) of eq. 6.1. S, D, E and
the emission sum are plain sums, so the estimate does not depend on merge order; N (and
so the future radius schedule) assumes locally uniform photon density when a batch was
gathered at a radius other than the current one, the same assumption PPM's flux
correction makes. All of it is float64 on the host.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


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
    if lit.any():
        lit_r2 = N[lit] / (math.pi * D[lit])
        r2 = np.minimum(r2, lit_r2.max())
        r2[lit] = lit_r2
    return np.sqrt(r2)


@dataclass
class Delta:
    """What a batch of passes adds: sums over its passes, each at the radius it read."""

    first_pass: int
    n_passes: int
    emitted: int  # photon paths emitted over the batch
    S: np.ndarray  # (pixels, 3) float64
    D: np.ndarray  # (pixels,) float64
    Ld: np.ndarray  # (pixels, 3) float64, directly seen emission summed over passes

    @property
    def pass_ids(self) -> range:
        return range(self.first_pass, self.first_pass + self.n_passes)


@dataclass
class Accumulators:
    """A job's shared per-pixel state (float64)."""

    alpha: float
    R0: np.ndarray  # (pixels,) initial radius
    S: np.ndarray
    D: np.ndarray
    N: np.ndarray
    Ld: np.ndarray
    emitted: int = 0
    passes: int = 0

    @classmethod
    def start(cls, alpha: float, R0: np.ndarray) -> "Accumulators":
        """Empty state: no pass merged, every radius at its initial value."""
        if not 0.0 < alpha <= 1.0:
            raise ValueError("alpha must lie in (0, 1]")
        n = len(R0)
        return cls(alpha=alpha, R0=np.asarray(R0, np.float64), S=np.zeros((n, 3)), D=np.zeros(n),
                   N=np.zeros(n), Ld=np.zeros((n, 3)))

    def radius(self) -> np.ndarray:
        return radius(self.R0, self.N, self.D)

    def merge(self, delta: Delta) -> None:
        """Add a batch. Commutative in S, D, E, Ld; N uses the radius at merge time."""
        r2_now = self.radius() ** 2
        self.N += self.alpha * math.pi * r2_now * delta.D
        self.S += delta.S
        self.D += delta.D
        self.Ld += delta.Ld
        self.emitted += delta.emitted
        self.passes += delta.n_passes

    def radiance(self) -> np.ndarray:
        """Current estimate L = S/E + Ld/passes, (pixels, 3) float64."""
        if self.passes == 0:
            return np.zeros_like(self.S)
        photon = self.S / self.emitted if self.emitted > 0 else np.zeros_like(self.S)
        return photon + self.Ld / self.passes
