"""Spectra to linear sRGB, as Mitsuba 3's RGB variants convert them when they read a scene.

A spectrum s(lambda) (piecewise linear between its samples, zero outside them) becomes CIE
1931 XYZ with the 2-degree colour matching functions over 360..830 nm, then linear sRGB
(IEC 61966-2-1's matrix). The illuminant depends on what the spectrum describes:

- reflectance: seen under D65 and normalised by it, XYZ = int s D65 xyz / int D65 y, so a
  flat reflectance r is grey r; the result is clamped to [0, 1] (a reflectance is bounded);
- unbounded (a conductor's eta and k): as a reflectance, but only negative components are
  clamped (to 0), as Mitsuba's parser converts those properties (checked with mi.traverse);
- emission: under the equal-energy illuminant, XYZ = int s xyz / int y, so a flat radiance
  L is XYZ (L, L, L), not grey in sRGB.

The integrals are Riemann sums over INTEGRATION_STEPS evenly spaced wavelengths from 360 to
830 nm, as Mitsuba's parser computes them: a spectrum that starts or ends inside that range
(a step) is then weighted as Mitsuba weights it. The CIE and D65 tables are colour-science's
(CIE 015:2018 data at 1 nm, linearly interpolated).
"""

from __future__ import annotations

import math
from functools import lru_cache
from typing import Literal

import numpy as np

CIE_MIN, CIE_MAX = 360.0, 830.0  # nm: the matching functions' range used for the integrals
INTEGRATION_STEPS = 1000
# Planck's law constants (CODATA 2014, as SI values).
PLANCK_H, LIGHT_C, BOLTZMANN_K = 6.62607004e-34, 2.99792458e8, 1.38064852e-23
Kind = Literal["reflectance", "unbounded", "emission"]  # what a spectrum describes (module docstring)


@lru_cache(maxsize=1)
def _tables() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(wavelengths, xyz matching functions (n, 3), D65 (n,), sRGB-from-XYZ matrix) at the
    integration's wavelengths."""
    import colour

    table = np.arange(CIE_MIN, CIE_MAX + 1.0)
    cmfs = np.asarray(colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"][table], np.float64)
    d65 = colour.SDS_ILLUMINANTS["D65"].copy().align(colour.SpectralShape(CIE_MIN, CIE_MAX, 1))
    wavelengths = np.linspace(CIE_MIN, CIE_MAX, INTEGRATION_STEPS)
    xyz = np.stack([np.interp(wavelengths, table, cmfs[:, i]) for i in range(3)], axis=1)
    illuminant = np.interp(wavelengths, table, np.asarray(d65.values, np.float64))
    matrix = np.asarray(colour.models.RGB_COLOURSPACE_sRGB.matrix_XYZ_to_RGB, np.float64)
    return wavelengths, xyz, illuminant, matrix


def sampled_to_rgb(wavelengths: np.ndarray, values: np.ndarray, kind: Kind) -> tuple[float, float, float]:
    """Linear sRGB of a sampled spectrum (increasing `wavelengths` in nm) describing `kind`."""
    grid, xyz, d65, matrix = _tables()
    s = np.interp(grid, wavelengths, values, left=0.0, right=0.0)
    weight = np.ones_like(grid) if kind == "emission" else d65
    tristimulus = (s * weight) @ xyz / float(weight @ xyz[:, 1])
    rgb = matrix @ tristimulus
    if kind == "reflectance":
        rgb = np.clip(rgb, 0.0, 1.0)
    elif kind == "unbounded":
        rgb = np.maximum(rgb, 0.0)
    return float(rgb[0]), float(rgb[1]), float(rgb[2])


def uniform_to_rgb(value: float, kind: Kind) -> tuple[float, float, float]:
    """Linear sRGB of a flat spectrum: grey unless an emission, which is XYZ (v, v, v)."""
    if kind != "emission":
        return value, value, value
    rgb = _tables()[3] @ np.full(3, value)
    return float(rgb[0]), float(rgb[1]), float(rgb[2])


def blackbody(wavelengths: np.ndarray, temperature: float) -> np.ndarray:
    """Planck's spectral radiance B(lambda, T) = 2 h c^2 / lambda^5 / (exp(h c / (lambda k T)) - 1),
    in W m^-2 sr^-1 per nm (Mitsuba's unit for a blackbody emitter)."""
    lam = np.asarray(wavelengths, np.float64) * 1e-9
    with np.errstate(over="ignore"):
        exponent = PLANCK_H * LIGHT_C / (lam * BOLTZMANN_K * temperature)
        return 1e-9 * 2 * PLANCK_H * LIGHT_C ** 2 / lam ** 5 / np.expm1(exponent)


def blackbody_to_rgb(temperature: float) -> tuple[float, float, float]:
    """Linear sRGB of a blackbody emitter at `temperature` kelvin (its radiance, unscaled)."""
    if not (math.isfinite(temperature) and temperature > 0):
        raise ValueError("temperature must be a positive number of kelvin")
    grid = _tables()[0]
    return sampled_to_rgb(grid, blackbody(grid, temperature), "emission")


def parse_spd(text: str) -> tuple[np.ndarray, np.ndarray]:
    """Wavelengths and values of a Mitsuba .spd file: one `wavelength value` pair a line, `#` comments.
    ValueError with the line if it is not that."""
    pairs = []
    for number, line in enumerate(text.splitlines(), 1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        parts = line.split()
        try:
            if len(parts) != 2:
                raise ValueError
            pairs.append((float(parts[0]), float(parts[1])))
        except ValueError:
            raise ValueError(f"line {number}: expected 'wavelength value', got {line[:40]!r}") from None
    return check_samples([p[0] for p in pairs], [p[1] for p in pairs])


def check_samples(wavelengths: list[float], values: list[float]) -> tuple[np.ndarray, np.ndarray]:
    """Samples as arrays; ValueError unless at least one, finite, with increasing wavelengths."""
    w, v = np.asarray(wavelengths, np.float64), np.asarray(values, np.float64)
    if len(w) == 0:
        raise ValueError("a spectrum needs at least one wavelength:value pair")
    if not (np.all(np.isfinite(w)) and np.all(np.isfinite(v))):
        raise ValueError("non-finite wavelength or value")
    if np.any(np.diff(w) <= 0):
        raise ValueError("wavelengths must increase")
    return w, v
