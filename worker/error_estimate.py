"""Progressive error estimation (dissertation chapter 6; digest section 4).

Per pixel, a stochastic bound on the error of the photon-density estimate (luminance),
from the additive sums of worker/stats.py after i passes with E photons emitted (the
adaptive sampler's sums are in uniform photons too, worker/adaptive.py):

    L      = Y(S) / E                          the estimate (smooth kernel, eq. 6.34)
    lap L  = G / E                             its Laplacian, from the kernel's (tangent plane)
    B      = 0.5 c GR / E                      bias, eq. 6.18: GR sums each pass's Laplacian
                                               term times its own radius R_j^2, so B is the
                                               mean of the passes' biases 0.5 R_j^2 c lap L
    V      = (X2 - X1^2 / i) / (i - 1)         eq. 6.22: sample variance of x_j = L_pj - B_j
    noise  = t(1 - beta/2, i - 1) sqrt(V / i)  eq. 6.10 half-width; Student t with i - 1
                                               degrees of freedom (i samples; the text's
                                               "degree i" is one too many)
    bound  = noise + max(|B| - z s_B, 0, B_e)  eq. 6.12 with only the significant part of B,
                                               or the discontinuity bias B_e below

The bias estimate is itself noisy: lap L comes from the same photons, with per-pass
samples whose spread gives the standard error s_B of B (from L2). Eq. 6.12 adds |B| as if
it were exact, so under uniform light (true bias 0) the noise of B alone would inflate the
bound. So the bound adds only the part of |B| beyond z = 1.25 of its standard errors s_B
(soft thresholding): a larger z drops the real bias of caustic edges, a smaller one keeps
some noise (coverage by z: docs/results.md). `bias` reports the plain eq. 6.18 (or,
where the bound uses the discontinuity bias below, its estimate EDGE_FACTOR dh). Eq. 6.19's
shortcut, the current radius R_i for every pass, would report alpha times the bias: under
the radius schedule the passes' mean R_j^2 is R_i^2 / alpha (worker/stats.py: a_k = A(k)
alpha / k), which also scales s_B.

Discontinuities. The Laplacian describes the bias only where the density is smooth within
the disc; at a shadow edge, a spot light's cone edge or a surface boundary it is no
estimate of it (dissertation 6.6: not consistent there), and the bound would under-cover
more as passes go on. So every
pass also gathers at r/2 from the same photons: Dh sums the change dh = L_p(r) - L_p(r/2).
Where the density is smooth the bias grows as r^2, so dh = 3/4 B. Where the mean dh
contradicts that by more than EDGE_SIGNIFICANCE standard errors, the density is not smooth
within the disc, and the bias bound becomes B_e = EDGE_FACTOR x (|dh| - EDGE_MARGIN s_dh):
a bias linear in r (an edge inside the disc) changes by half between the radii, and an
edge between r/2 and r puts all the bias into dh. Pixels within about 0.17 r of an edge
have more bias than 2 dh, but their pixel footprint straddles the edge. Both z's are
normal quantiles taken as Student t quantiles with i - 1 degrees of freedom.
EDGE_SIGNIFICANCE and EDGE_MARGIN trade edges found against false detections in smooth
scenes. With the stochastic hash the r/2 estimate rests on one or two photons, too
heavy-tailed for the test, so the integrator uses B_e with the exact gather only.

The constant c. The dissertation writes c = k2 = 10 pi / 168 (k2 the unnormalised second
moment of K over the unit disc); that reproduces its Fig. 6.1 (the cubic ramp's RMS ratio
7.90) but is 4 pi / 7 = 1.8x the first-order Taylor bias of a kernel normalised by k1 R^2,
whose constant is c = k2 / (2 k1) = 5/48. The default is "taylor": it is the estimate of
the bias of the estimator we compute, and an overestimated bias only delays termination.
"dissertation" reproduces the paper's numbers.

Never-lit pixels. A pixel that had measurement points but never found a photon (D = 0)
has no sample variance, but its zero count is evidence: with E photons emitted and every
pass's disc at least as large as the current radius R (radii only shrink), an expected
density of rho photons per unit area per emitted photon would have put at least
rho pi R^2 E photons into its discs, and zero were found. The one-sided Poisson bound at
confidence c gives rho pi R^2 E <= -ln(1 - c), and so

    L <= q (-ln(1 - c)) / (pi R^2 E)       (reported as the pixel's noise; bias 0)

where E counts only the photons of passes in which the pixel had a measurement point.

with q the luminance a photon contributes per unit photon density, Y(S) / D, taken as its
largest value over pixels that found at least UNLIT_MIN_PHOTONS photons: the assumption is
that a photon reaching the dark pixel would carry no more than the brightest well-sampled
pixel's. The bound falls like 1 / (R^2 E), so a region no light reaches converges too.
Its relative error is capped at 1: an estimate of 0 is off by at most max(L, floor).

The image average. Per pixel, relative error = bound / max(L, floor), floor =
FLOOR_FRACTION x the mean L of lit pixels, so dim pixels are measured against a visible
fraction of the image. The image's average is the mean of the pixels' relative errors
weighted by max(L, floor), that is sum(bound) / sum(max(L, floor)) over a group of pixels
(a relative L1 error): a pixel's error counts in proportion to the light it holds. So a
thin ring of dim pixels at a small lit region's edge, whose bounds are large against their
own luminance and shrink only with the radius, cannot hold the average up, while an edge
that is wrong where the light is, bright pixels with large errors, weighs in full. The
average is the LARGER of two such means: over pixels that found photons, and over every
measured pixel (those that never found one included, each bound at most its weight). A
black region then cannot hold the average up forever (its errors fall with the bound
above), nor, by being most of the image, dilute the error of the lit part (which is
averaged on its own); and it raises the average in proportion to its size, so a few pixels
measured in a pass or two without a photon do not set the whole image's error to 100%.
With fewer than two passes the noise is unknown and the average is 1.

Direct light by next-event estimation (`direct: nee`). Then the image is the photon
estimate plus Ld / i, the mean of per-pass samples y_j = Y(Ld_j) (directly seen emission
plus the light and BSDF samples at the point). Its sample variance (from Ld2, the sum of
y_j^2) adds to the photon samples' variance as that of an independent part (the two use
independent random streams; the shared measurement point's covariance is ignored), also
for never-lit pixels, and relative errors are taken against the whole luminance.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy import special
from scipy import stats as scipy_stats

from kernels.contract import K1, K2, LUMINANCE
from worker.host_threads import each

if TYPE_CHECKING:
    from worker.stats import Accumulators

BIAS_CONSTANTS = {"taylor": K2 / (2.0 * K1), "dissertation": K2}
FLOOR_FRACTION = 0.05
BIAS_SIGNIFICANCE = 1.25  # standard errors a bias estimate must exceed to count in the bound
EDGE_SIGNIFICANCE = 2.0  # standard errors by which the change between radii must contradict a smooth density
EDGE_FACTOR = 2.0  # bias at r per unit of the change from r/2 to r where the density is not smooth
EDGE_MARGIN = 2.5  # standard errors of that change left out of the bias bound (soft thresholding)
UNLIT_MIN_PHOTONS = 16  # photons a pixel must have found to set the per-photon luminance q
FOLDED_STEPS = 3  # Newton steps of folded_quantile
BLOCK_PIXELS = 1 << 14  # pixels the estimate works on at a time: its temporaries stay in the CPU's cache


@dataclass(frozen=True)
class ErrorEstimate:
    luminance: np.ndarray  # L per pixel
    bias: np.ndarray  # B (signed)
    noise: np.ndarray  # half-width of the confidence interval
    bound: np.ndarray  # noise + |B|
    relative: np.ndarray  # bound / max(L, floor); 1 where unknown
    measured: np.ndarray  # pixels that had a measurement point
    known: np.ndarray  # measured pixels that ever found a photon (the rest: the zero-count bound)
    average: float  # the larger of the mean relative errors of known and of never-lit pixels
    confidence: float


def bias_estimate(radius: np.ndarray, G: np.ndarray, emitted: float, constant: str) -> np.ndarray:
    """B = 0.5 R^2 c lap L per pixel at radius R, lap L = G / E (zero before any photon was
    emitted): what a pass at R subtracts from its sample; computed in one array (a frame's
    temporaries cost more than the arithmetic)."""
    if emitted == 0:
        return np.zeros(len(radius))
    bias = np.square(radius)
    bias *= 0.5  # the order of 0.5 R^2 c G / E, left to right
    bias *= BIAS_CONSTANTS[constant]
    bias *= G
    bias /= emitted
    return bias


def student_t(confidence: float, dof: int) -> float:
    """Two-sided quantile t(1 - beta/2, dof) for confidence 1 - beta."""
    return float(scipy_stats.t.ppf(0.5 + 0.5 * confidence, dof))


def folded_quantile(mu: np.ndarray, sigma: np.ndarray, confidence: float, dof: int) -> np.ndarray:
    """Per element, the B >= 0 with P(|mu + sigma T| <= B) = confidence, T Student t with
    `dof` degrees of freedom: the symmetric bound on an error estimated as mu with standard
    error sigma (B = student_t sigma at mu = 0). B lies between |mu| plus sigma times the
    one-sided and the two-sided quantile; for confidence >= 1/2 that is beyond |mu|, where
    P(|mu + sigma T| <= B) is concave in B (both tails' densities fall), so Newton's steps
    from the upper end reach the root from below after the first, quadratically
    (FOLDED_STEPS of them: within 1e-5 of the confidence)."""
    mu = np.abs(mu)
    sigma = np.maximum(sigma, np.finfo(np.float64).tiny)
    lo = mu + sigma * float(scipy_stats.t.ppf(confidence, dof))
    b = mu + sigma * student_t(confidence, dof)
    for _ in range(FOLDED_STEPS):
        upper, lower = (b - mu) / sigma, (-b - mu) / sigma
        inside = special.stdtr(dof, upper) - special.stdtr(dof, lower)
        slope = (scipy_stats.t.pdf(upper, dof) + scipy_stats.t.pdf(lower, dof)) / sigma
        b = np.maximum(b - (inside - confidence) / slope, lo)
    return b


def unlit_scale(state: Accumulators, lum: np.ndarray, known: np.ndarray, confidence: float) -> float:
    """q (-ln(1 - c)) of the zero-count bound q (-ln(1 - c)) / (pi R^2 E) (module docstring):
    q from the pixels that found photons, a block at a time; inf where nothing is known yet
    (no photon found anywhere, or none emitted)."""
    emitted = state.emitted
    if emitted == 0 or not known.any():
        return math.inf
    r = state.radius()
    q_counted = q_known = -math.inf
    for blk in blocks(len(lum)):
        k = known[blk]
        if not k.any():
            continue
        D = state.D[blk][k]
        per_photon = lum[blk][k] * emitted / D  # Y(S) / D
        counted = D * math.pi * r[blk][k] ** 2 >= UNLIT_MIN_PHOTONS
        q_known = max(q_known, float(per_photon.max()))
        if counted.any():
            q_counted = max(q_counted, float(per_photon[counted].max()))
    q = q_counted if q_counted > -math.inf else q_known
    return q * -math.log1p(-confidence)


def unlit_bound(state: Accumulators, scale: float, blk: slice) -> np.ndarray:
    """Per pixel of a block, the zero-count bound `scale` / (pi R^2 E), E counting the photons
    emitted while the pixel had a measurement point (`scale` from `unlit_scale`)."""
    if math.isinf(scale):
        return np.full(blk.stop - blk.start, np.inf)
    r2 = state.radius()[blk] ** 2
    exposed = state.emitted * state.H[blk] / state.passes
    with np.errstate(divide="ignore"):
        return scale / (math.pi * r2 * exposed)


def discontinuity_bias(Dh: np.ndarray, Dh2: np.ndarray, i: int, bias: np.ndarray, bias_se: np.ndarray,
                       z_rough: float, z_margin: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where the density is not smooth within the disc (module docstring): the mask of
    pixels whose mean change dh of the per-pass estimate from radius r/2 to r (sums Dh, Dh2
    over i passes) contradicts the smooth prediction 3/4 B, the bias estimate EDGE_FACTOR dh
    there, and its part beyond EDGE_SIGNIFICANCE standard errors (the bound's B_e; zero
    elsewhere). `z_rough` and `z_margin` are EDGE_SIGNIFICANCE and EDGE_MARGIN as Student t
    quantiles (`edge_quantiles`)."""
    dh = Dh / i
    dh_se = np.sqrt(np.maximum(Dh2 - Dh ** 2 / i, 0.0) / (i - 1) / i)
    rough = np.abs(dh - 0.75 * bias) > z_rough * np.sqrt(dh_se ** 2 + (0.75 * bias_se) ** 2)
    significant = np.where(rough, EDGE_FACTOR * np.maximum(np.abs(dh) - z_margin * dh_se, 0.0), 0.0)
    return rough, EDGE_FACTOR * dh, significant


def edge_quantiles(i: int) -> tuple[float, float]:
    """EDGE_SIGNIFICANCE and EDGE_MARGIN standard errors from i samples: the normal z's as
    Student t quantiles with i - 1 degrees of freedom."""
    z_rough, z_margin = (student_t(math.erf(z / math.sqrt(2.0)), i - 1) for z in (EDGE_SIGNIFICANCE, EDGE_MARGIN))
    return z_rough, z_margin


def blocks(n: int) -> list[slice]:
    """The pixels a block at a time (BLOCK_PIXELS)."""
    return [slice(at, min(n, at + BLOCK_PIXELS)) for at in range(0, n, BLOCK_PIXELS)]


@dataclass(frozen=True)
class _Round:
    """What every block of one estimate shares: the state, the settings and the quantiles."""

    state: Accumulators
    constant: str
    significance: float
    discontinuities: bool
    t: float
    z_rough: float
    z_margin: float
    unlit_scale: float


def _block(run: _Round, blk: slice, direct: np.ndarray | None, dark: np.ndarray,
           out: dict[str, np.ndarray]) -> None:
    """Bias, noise and bound of one block of pixels (module docstring), into `out`."""
    state, i = run.state, run.state.passes
    r = state.radius()[blk]
    r2 = r ** 2
    G = state.G[blk]
    bias = bias_estimate(np.ones(len(r)), state.GR[blk], state.emitted, run.constant)  # eq. 6.18
    n = len(r)
    if i >= 2:
        # Noise: the per-pass samples' variance (and with NEE its direct light's).
        direct_var = np.maximum(state.Ld2[blk] - i * direct ** 2, 0.0) / (i - 1) if direct is not None else 0.0
        var = np.maximum(state.X2[blk] - state.X1[blk] ** 2 / i, 0.0) / (i - 1) + direct_var
        noise = run.t * np.sqrt(var / i)
        direct_noise = run.t * np.sqrt(direct_var / i)
        # The bias estimate's standard error, from the per-pass Laplacians.
        emitted = state.emitted
        lap_sum = G / (emitted / i) if emitted > 0 else np.zeros(n)  # sum of each pass's lap L
        lap_var = np.maximum(state.L2[blk] - lap_sum ** 2 / i, 0.0) / (i - 1)
        bias_se = 0.5 * r2 / state.alpha * BIAS_CONSTANTS[run.constant] * np.sqrt(lap_var / i)
        bias_noise = run.significance * bias_se
        # The discontinuity bias.
        rough, edge_estimate, edge_bias = discontinuity_bias(state.Dh[blk], state.Dh2[blk], i, bias, bias_se,
                                                             run.z_rough, run.z_margin)
        if run.discontinuities:  # report the bias the bound uses: eq. 6.20, or B_e where the density is rough
            bias = np.where(rough & (edge_bias > np.maximum(np.abs(bias) - bias_noise, 0.0)), edge_estimate, bias)
        else:
            edge_bias = np.zeros(n)
    else:
        noise = bias_noise = direct_noise = np.full(n, np.inf)
        edge_bias = np.zeros(n)
    # Never-lit pixels: the zero-count bound.
    if dark.any():
        noise = np.where(dark, unlit_bound(state, run.unlit_scale, blk) + direct_noise, noise)
    significant_bias = np.maximum(np.maximum(np.abs(bias) - bias_noise, 0.0), edge_bias)
    out["bias"][blk] = bias
    out["noise"][blk] = noise
    np.add(noise, significant_bias, out=out["bound"][blk])


def estimate(state: Accumulators, confidence: float, constant: str = "taylor",
             significance: float = BIAS_SIGNIFICANCE, discontinuities: bool = True) -> ErrorEstimate:
    """The error bound per pixel and its image average; `significance` is z above;
    `discontinuities=False` leaves out the discontinuity bias B_e (for comparison).
    Per-pixel work goes a block of pixels at a time (BLOCK_PIXELS): a whole frame's
    temporaries would cost more in memory traffic and page faults than the arithmetic."""
    if not 0.0 < confidence < 1.0:
        raise ValueError("confidence must lie in (0, 1)")
    i = state.passes
    lum = np.empty(len(state.H))
    for blk in blocks(len(lum)):
        lum[blk] = state.photon_radiance(blk) @ LUMINANCE
    nee = "Ld2" in state.sums  # direct light by NEE: its per-pass samples are part of the estimate
    direct = state.Ld @ LUMINANCE / max(i, 1) if nee else None
    measured = state.H > 0
    known = measured & (state.D > 0.0)
    dark = measured & ~known
    t = student_t(confidence, i - 1) if i >= 2 else math.inf
    z_rough, z_margin = edge_quantiles(i) if i >= 2 else (math.inf, math.inf)
    run = _Round(state, constant, significance, discontinuities, t, z_rough, z_margin,
                 unlit_scale(state, lum, known, confidence) if dark.any() else math.inf)  # (used only where dark)
    out = {name: np.empty(len(lum)) for name in ("bias", "noise", "bound")}
    state.radius()  # computed once, before the blocks share it
    each(lambda blk: _block(run, blk, None if direct is None else direct[blk], dark[blk], out), blocks(len(lum)))
    if direct is not None:
        lum += direct
    # Relative errors against a floor, and the image average.
    lit = measured & (lum > 0.0)
    floor = FLOOR_FRACTION * float(lum[lit].mean()) if lit.any() else 1.0
    bound, relative = out["bound"], np.empty(len(lum))
    with np.errstate(invalid="ignore", divide="ignore"):
        for blk in blocks(len(lum)):
            relative[blk] = np.where(measured[blk] & np.isfinite(bound[blk]),
                                     bound[blk] / np.maximum(lum[blk], floor), 1.0)
    relative[dark] = np.minimum(relative[dark], 1.0)  # an estimate of 0 is off by at most 100%
    average = image_average(relative, np.maximum(lum, floor), known, measured) if i >= 2 else 1.0
    return ErrorEstimate(luminance=lum, bias=out["bias"], noise=out["noise"], bound=bound, relative=relative,
                         measured=measured, known=known, average=average, confidence=confidence)


def actual_average(est: ErrorEstimate, truth: np.ndarray) -> float:
    """The image's actual average relative error against a known answer (luminance per
    pixel), by the definition the estimate uses: |L - truth| / max(truth, floor), floor =
    FLOOR_FRACTION x the mean truth of lit pixels, averaged as `image_average` does with
    weights max(truth, floor)."""
    truth = np.broadcast_to(np.asarray(truth, np.float64), est.luminance.shape)
    lit = truth > 0.0
    floor = FLOOR_FRACTION * float(truth[lit].mean()) if lit.any() else 1.0
    weight = np.maximum(truth, floor)
    return image_average(np.abs(est.luminance - truth) / weight, weight, est.known, est.measured)


def image_average(relative: np.ndarray, weight: np.ndarray, known: np.ndarray, measured: np.ndarray) -> float:
    """The larger of the `weight`ed mean relative error over pixels that found photons
    (`known`) and over every measured pixel, those that never did included (module
    docstring; weight = max(L, floor)); 1 if no pixel was measured."""
    means = [float(np.sum(relative * weight, where=group) / np.sum(weight, where=group))
             for group in (known, measured) if group.any()]
    return max(means) if means else 1.0
