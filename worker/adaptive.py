"""Adaptive photon tracing (`sampler: adaptive`), the host half: the job's counters, the
visible fraction V_c, the mutation size theta and the number of chains.

The kernels (kernels/photon_chains.cl) return per pass a few integer counters. A batch
adds them to its Delta and the store sums them into the job (worker/stats.py), like the
photon count: additive, so batches of any worker merge in any order. From the pooled sums:

    V_c   = visible uniform draws / uniform draws          (Hachisuka & Jensen 2011, eq. 5)

which sizes the chains and decides whether they mutate. The image does not use it: each
chain pass's photon counts are scaled on the device, before its gather, by

    photons per pass * V_k / splats_k                      (pass_scale)

with V_k that pass's own visible fraction, so the pass's sums (flux, and the photon count
the radius rule reads) are in uniform photons and the image is S / E as for uniform tracing.
Every splat is a sample of F = V / V_k whatever the pass's pattern of visible draws (a
chain starts from an exact sample and replica exchange and mutations keep F), so
E[V_k S_k / splats_k] = I_k, the uniform pass's expectation: per pass, not only pooled.
Why not the pooled V_c (the paper's): (1) SPPM's radius rule (N = alpha M_1, then
(N + alpha M) / (N + M)) shrinks as intended only if every pass brings the same expected
count, which uniform photons do whatever a pass's iterations; (2) a V_c pooled over passes
whose V_k drifts as the radius shrinks is biased (mean V times mean 1 / V).

theta is the mutation size of every pass of a batch, chosen from the job's merged counters so
that the chains' acceptance A(theta) meets the target A* (the controlled-MCMC goal of eq. 11,
dissertation 8.2). theta takes values on a grid, theta_j = exp(j THETA_BIN) within
[THETA_MIN, THETA_MAX], and each pass adds its mutations and acceptances to its grid point's
counters (`binned`). From the pooled acceptance per grid point, made non-increasing in theta
by isotonic regression (pool adjacent violators, weighted by mutations: a larger mutation is
never more likely accepted), the next theta is where logit(A) crosses logit(A*) on the line,
in log theta, through the two grid points that bracket the crossing (a secant step), or, with
no bracket yet, through the two points nearest it (one point: slope PRIOR_SLOPE), rounded to
the grid and clamped to the range. So theta is a function of the merged counters alone, not
of how they split into batches or how many batches ran at once: concurrent batches from one
state all use the same theta and only add evidence at its grid point; integer sums make it
bit-exact whatever order batches merged in, and a re-issued batch given the same state
replays its passes bit for bit.
"""

from __future__ import annotations

import math

# Counters a pass adds, in the kernel's order (kernels/photon_chains.cl, CTR_*).
COUNTERS = ("draws", "visible", "splats", "mutations", "accepted", "started", "boot")  # boot: the starts' draws
THETA_MIN, THETA_MAX = 1e-3, 64.0  # "bounding theta to a large finite range" (dissertation 8.2)
THETA_BIN = math.log(2.0) / 4.0  # the grid of theta: four points an octave
PRIOR_SLOPE = -1.0  # d logit(A) / d log theta assumed until two grid points measure it
LOGIT_CLAMP = 1e-4  # acceptances are taken within [this, 1 - this] in logit
MIN_EVIDENCE = 64  # mutations at a grid point before its acceptance counts
MIN_GAIN = 12.0  # chains mutate only while they promise this many times uniform tracing's visible paths (mutates)
ITERATION_COST = 8  # a chain iteration costs about this many uniform photon paths (iterations)
CHAIN_SHARE = 0.05  # chains = this share of the visible paths a pass expects (a chain's start costs 1 / V_c draws)
MIN_CHAINS, MAX_CHAINS = 16, 4096
MIN_BOOT_DRAWS = 256  # a chain's start: at least this many uniform draws, else photons / chains
VISIBILITY_SAMPLE = 16  # a pass whose chains do not mutate judges one uniform draw in this many, for V_c ...
JUDGE_EVERY = 8  # ... in one pass of this many (pass index 0, 8, 16, ...); the others are uniform passes alone


def theta_index(theta_value: float) -> int:
    """The grid point of a mutation size."""
    return round(math.log(theta_value) / THETA_BIN)


def binned(theta_value: float, mutations: int, accepted: int) -> dict[str, int]:
    """A pass's counters for the grid point of the theta it used."""
    j = theta_index(theta_value)
    return {f"mutations_at_{j}": mutations, f"accepted_at_{j}": accepted} if mutations else {}


def theta(counters: dict[str, int], target: float) -> float:
    """The mutation size for a batch starting from these merged counters (module docstring)."""
    points = sorted((j, counters[f"accepted_at_{j}"], m) for j, m in _evidence(counters))
    if not points:
        return 1.0
    fitted = _non_increasing([a / m for _, a, m in points], [m for _, _, m in points])
    x = [j * THETA_BIN for j, _, _ in points]  # log theta
    y = [_logit(a) for a in fitted]
    above = [i for i, a in enumerate(fitted) if a >= target]  # theta too small there
    if above and len(above) < len(points):  # a bracket: the points on either side of the crossing
        i0, i1 = above[-1], above[-1] + 1
    elif above:  # every theta tried is too small: extrapolate from the largest two
        i0, i1 = max(len(points) - 2, 0), len(points) - 1
    else:
        i0, i1 = 0, min(1, len(points) - 1)
    slope = (y[i1] - y[i0]) / (x[i1] - x[i0]) if y[i1] < y[i0] else PRIOR_SLOPE
    ref = i1 if above else i0  # on the line either point; with the prior slope, the one nearest the crossing
    j = (x[ref] + (_logit(target) - y[ref]) / slope) / THETA_BIN
    return math.exp(min(max(round(j), theta_index(THETA_MIN)), theta_index(THETA_MAX)) * THETA_BIN)


def _logit(a: float) -> float:
    a = min(max(a, LOGIT_CLAMP), 1.0 - LOGIT_CLAMP)
    return math.log(a / (1.0 - a))


def _evidence(counters: dict[str, int]) -> list[tuple[int, int]]:
    """(grid point, mutations) of every grid point with at least MIN_EVIDENCE mutations."""
    prefix = "mutations_at_"
    return [(int(name[len(prefix):]), m) for name, m in counters.items()
            if name.startswith(prefix) and m >= MIN_EVIDENCE]


def _non_increasing(values: list[float], weights: list[int]) -> list[float]:
    """The weighted least-squares non-increasing fit of `values` (pool adjacent violators)."""
    blocks: list[list[float]] = []  # [mean, weight, count]
    for v, w in zip(values, weights, strict=True):
        blocks.append([v, float(w), 1])
        while len(blocks) > 1 and blocks[-2][0] < blocks[-1][0]:
            v2, w2, n2 = blocks.pop()
            v1, w1, n1 = blocks[-1]
            blocks[-1] = [(v1 * w1 + v2 * w2) / (w1 + w2), w1 + w2, n1 + n2]
    return [b[0] for b in blocks for _ in range(int(b[2]))]


def gain(v_c: float, target: float) -> float:
    """The chains' new visible paths per traced path over uniform tracing's (V_c). A chain
    iteration traces a uniform draw and, when it is invisible, a mutation; it finds a new
    visible path with probability V_c + (1 - V_c) A, A the acceptance (held at the target),
    so per traced path (V_c + (1 - V_c) A) / (2 - V_c), against V_c for uniform tracing."""
    if v_c <= 0.0:
        return math.inf
    return (v_c + (1.0 - v_c) * target) / ((2.0 - v_c) * v_c)


def mutates(counters: dict[str, int], target: float) -> bool:
    """Whether a batch's chains mutate: only while their gain over uniform tracing (gain,
    from the pooled V_c; 1 at V_c ~ A*) is at least MIN_GAIN; never before any V_c (a job's
    first pass). A gain of 1 is not enough: the chains' visible paths are correlated and
    each costs a judged trace and a gather (docs/results.md, "Adaptive photon tracing").
    Otherwise the pass is uniform tracing (the paper's "automatically uses uniform random
    sampling", made exact), plus, in one pass of JUDGE_EVERY, the visibility of
    1 / VISIBILITY_SAMPLE of its draws for V_c (sample_iterations, judges). Mutations resume
    if the pooled V_c falls far enough."""
    v_c = visible_fraction(counters)
    return v_c is not None and gain(v_c, target) >= MIN_GAIN


def visible_fraction(counters: dict[str, int]) -> float | None:
    """V_c from the pooled uniform draws; None before any."""
    draws = counters.get("draws", 0)
    return counters.get("visible", 0) / draws if draws > 0 else None


def pass_scale(counts: dict[str, int], photons: int) -> float:
    """What a chain pass's photon counts are multiplied by so that its sums are in uniform
    photons, as a uniform pass of `photons` paths would make them: photons * V_k / splats,
    V_k the pass's own visible fraction (0 if the pass splatted nothing)."""
    if counts["splats"] == 0 or counts["draws"] == 0:
        return 0.0
    return photons * counts["visible"] / (counts["draws"] * counts["splats"])


def iterations(photons: int) -> int:
    """Chain iterations for a pass whose user asked for `photons` photon paths: as many as
    cost about what tracing them would (ITERATION_COST uniform paths an iteration: its one
    or two judged traces, the state's cache and the gather of the visible photons it keeps).
    The pass's sums are in uniform photons whatever its iterations (pass_scale), so this
    sets its cost and noise, not its radius schedule."""
    return max(1, photons // ITERATION_COST)


def sample_iterations(photons: int) -> int:
    """Uniform draws judged for V_c in a pass whose chains do not mutate (mutates)."""
    return max(1, photons // VISIBILITY_SAMPLE)


def judges(pass_index: int) -> bool:
    """Whether a pass whose chains do not mutate judges its sample of draws for V_c (one in
    JUDGE_EVERY). The others are the uniform photon pass with nothing more: the judged
    sample needs a grid over the pass's points and a kernel of its own."""
    return pass_index % JUDGE_EVERY == 0


def chains(counters: dict[str, int], iterations: int) -> int:
    """Chains for a pass of `iterations` chain iterations: CHAIN_SHARE of the visible paths
    it expects (K <= 0.05 V_c photons keeps the starts' cost near 5% of the pass), within bounds."""
    v_c = visible_fraction(counters)
    k = MIN_CHAINS if v_c is None else round(CHAIN_SHARE * v_c * iterations)
    return max(1, min(iterations, MAX_CHAINS, max(MIN_CHAINS, k)))


def boot_draws(n_chains: int, photons: int) -> int:
    """Cap on the uniform draws of a chain's start: with nothing visible, the starts cost
    about one pass of photons (or MIN_BOOT_DRAWS a chain)."""
    return max(MIN_BOOT_DRAWS, -(-photons // n_chains))
