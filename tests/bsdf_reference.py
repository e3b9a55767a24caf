"""The BSDFs of the scene model in numpy, written from their equations (kernels/bsdf.cl
states them) for the closed forms the tests compare renders with: f(wo, wi) without the
cosine, for directions as (..., 3) arrays and the normal `n` of the side they leave from.

Only reflection: what a point light gives a plane, and a convex object's directional albedo
in a uniform field, need no more (a rough glass's reflected part alone).
"""

from __future__ import annotations

import math

import numpy as np

from worker.scene import Glossy, Plastic, RoughConductor, RoughGlass, RoughPlastic
from worker.surfaces import coat_constants, fresnel, smith_g1, table_cosines


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.einsum("...k,...k->...", a, b)


def fresnel_conductor(c: np.ndarray, eta: np.ndarray, k: np.ndarray) -> np.ndarray:
    """Unpolarised reflectance of eta + i k at cos c, from the complex Fresnel equations
    (s and p amplitudes with the complex cosine of the transmitted wave), per channel."""
    c = np.asarray(c, np.float64)[..., None]
    n = eta + 1j * k
    cos_t = np.sqrt(1.0 - (1.0 - c ** 2) / n ** 2)
    rs = (c - n * cos_t) / (c + n * cos_t)
    rp = (n * c - cos_t) / (n * c + cos_t)
    return 0.5 * (np.abs(rs) ** 2 + np.abs(rp) ** 2)


def microfacet_d(cos_h: np.ndarray, alpha: float, beckmann: bool) -> np.ndarray:
    c2 = np.clip(cos_h, 1e-12, 1.0) ** 2
    t2 = (1.0 - c2) / c2
    if beckmann:
        d = np.exp(-t2 / alpha ** 2) / (math.pi * alpha ** 2 * c2 ** 2)
    else:
        d = alpha ** 2 / (math.pi * c2 ** 2 * (alpha ** 2 + t2) ** 2)
    return np.where(cos_h > 0.0, d, 0.0)


def bsdf(material: object, n: np.ndarray, wo: np.ndarray, wi: np.ndarray) -> np.ndarray:
    """f(wo, wi), rgb, (..., 3), for reflection on the side n faces."""
    co, ci = _dot(wo, n), _dot(wi, n)
    up = ((co > 0.0) & (ci > 0.0))[..., None]
    if isinstance(material, Glossy):
        mirror = 2.0 * co[..., None] * n - wo
        ca = np.clip(_dot(wi, mirror), 0.0, None)
        e = material.exponent
        return np.where(up, np.array(material.albedo) * ((e + 2.0) / (2.0 * math.pi) * ca ** e)[..., None], 0.0)
    h = wo + wi
    h = h / np.linalg.norm(h, axis=-1, keepdims=True)
    oh, ch = _dot(wo, h), _dot(h, n)
    out = np.zeros(np.broadcast_shapes(co.shape, ci.shape) + (3,))
    if isinstance(material, RoughConductor | RoughPlastic | RoughGlass):
        beckmann = material.distribution == "beckmann"
        g = smith_g1(co, oh, material.alpha, beckmann) * smith_g1(ci, oh, material.alpha, beckmann)
        lobe = microfacet_d(ch, material.alpha, beckmann) * g / (4.0 * np.abs(co) * np.abs(ci))
        if isinstance(material, RoughConductor):
            r = np.array(material.specular) * (1.0 if material.eta is None else
                                               fresnel_conductor(oh, np.array(material.eta), np.array(material.k)))
        else:
            tint = material.albedo if isinstance(material, RoughGlass) else material.specular
            r = np.array(tint) * fresnel(np.clip(oh, 0.0, 1.0), material.ior)[..., None]
        out = out + r * lobe[..., None]
    if isinstance(material, Plastic):
        internal, table = coat_constants(material)
        rho = np.array(material.albedo)
        inner = rho * internal if material.nonlinear else internal
        if table is None:
            t_o, t_i = 1.0 - fresnel(np.clip(co, 0.0, 1.0), material.ior), 1.0 - fresnel(np.clip(ci, 0.0, 1.0),
                                                                                            material.ior)
        else:
            t_o, t_i = np.interp(co, table_cosines(), table), np.interp(ci, table_cosines(), table)
        out = out + rho / (1.0 - inner) * (t_o * t_i / (material.ior ** 2 * math.pi))[..., None]
    return np.where(up, out, 0.0)


def rough_transmission(material: RoughGlass, n: np.ndarray, wo: np.ndarray, wi: np.ndarray,
                       eta: float) -> np.ndarray:
    """A rough glass's refraction f(wo, wi), rgb, in radiance mode: wo on n's side, wi beyond,
    eta = n(wi's side) / n(wo's side) (Walter et al. 2007, eq. 21, over eta^2)."""
    h = wo + eta * wi
    h = h / np.linalg.norm(h, axis=-1, keepdims=True)
    h = np.where((_dot(h, n) < 0.0)[..., None], -h, h)
    oh, ih, co, ci, ch = _dot(wo, h), _dot(wi, h), _dot(wo, n), _dot(wi, n), _dot(h, n)
    beckmann = material.distribution == "beckmann"
    g = smith_g1(co, oh, material.alpha, beckmann) * smith_g1(ci, ih, material.alpha, beckmann)
    f = ((1.0 - fresnel(np.clip(oh, 1e-12, 1.0), eta)) * microfacet_d(ch, material.alpha, beckmann) * g
         * np.abs(ih) * oh / ((ih + oh / eta) ** 2 * np.abs(ci) * co * eta ** 2))
    tint = material.albedo if material.transmittance is None else material.transmittance
    return np.where(((co > 0.0) & (ci < 0.0) & (oh > 0.0))[..., None], np.array(tint) * f[..., None], 0.0)
