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

theta is frozen within a pass and adapted between passes by the controlled-MCMC rule of
eq. 11, theta += gamma_k (A_k - A*), taken on log theta (theta spans 1e-3..64; a step of a
given size in log theta is the same relative change everywhere) and with gamma_k =
THETA_GAIN / sqrt(k + 1) for pass index k (diminishing: the sum of gamma_k diverges, each
step goes to 0). Each pass's step is a function of that pass alone (its index, the theta
it used and its own acceptance A_k), rounded to an integer number of THETA_QUANTUM and
summed like the other counters: log theta = (sum of steps) * THETA_QUANTUM, clamped to
[THETA_MIN, THETA_MAX]. So theta is a function of the merged state, integer sums make it
bit-exact whatever order batches merged in, and a re-issued batch given the same state
replays its passes bit for bit. A step that would push theta further beyond a bound is 0
(projection), so the sum cannot wind up there. Passes of one batch share the theta the
batch started with (the paper adapts after every mutation; a pass's thousands of
mutations already make A_k precise).
"""

from __future__ import annotations

import math

# Counters a pass adds, in the kernel's order (kernels/photon_chains.cl, CTR_*).
COUNTERS = ("draws", "visible", "splats", "mutations", "accepted", "started", "boot")  # boot: the starts' draws
THETA_STEPS = "theta_steps"  # the sum of the passes' log-theta steps, in THETA_QUANTUM
THETA_QUANTUM = 2.0 ** -24
THETA_MIN, THETA_MAX = 1e-3, 64.0  # "bounding theta to a large finite range" (dissertation 8.2)
THETA_GAIN = 4.0  # gamma_k = THETA_GAIN / sqrt(k + 1), in log theta per unit of acceptance error
MIN_GAIN = 12.0  # chains mutate only while they promise this many times uniform tracing's visible paths (mutates)
ITERATION_COST = 8  # a chain iteration costs about this many uniform photon paths (iterations)
CHAIN_SHARE = 0.05  # chains = this share of the visible paths a pass expects (a chain's start costs 1 / V_c draws)
MIN_CHAINS, MAX_CHAINS = 16, 4096
MIN_BOOT_DRAWS = 256  # a chain's start: at least this many uniform draws, else photons / chains
VISIBILITY_SAMPLE = 16  # a pass whose chains do not mutate judges one uniform draw in this many, for V_c ...
JUDGE_EVERY = 8  # ... in one pass of this many (pass index 0, 8, 16, ...); the others are uniform passes alone


def theta(counters: dict[str, int]) -> float:
    """The mutation size for a batch starting from these merged counters."""
    log_theta = counters.get(THETA_STEPS, 0) * THETA_QUANTUM
    return min(max(math.exp(log_theta), THETA_MIN), THETA_MAX)


def theta_step(pass_index: int, used: float, mutations: int, accepted: int, target: float) -> int:
    """Pass `pass_index`'s step of log theta (in THETA_QUANTUM), from its own acceptance."""
    if mutations == 0:
        return 0  # every uniform draw was visible (or no chain had a state): nothing to adapt
    error = accepted / mutations - target
    if (used >= THETA_MAX and error > 0.0) or (used <= THETA_MIN and error < 0.0):
        return 0
    return round(THETA_GAIN / math.sqrt(pass_index + 1.0) * error / THETA_QUANTUM)


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
