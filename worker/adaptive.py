"""Adaptive photon tracing, the host half: the job's counters, the visible fraction V_c,
the mutation size theta, the number of chains, and `sampler: auto`'s choice between chains
and uniform photon tracing.

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

`sampler: adaptive` runs chains in every pass. `sampler: auto` (the default) measures first:
a job's passes 0 .. MEASURE_PASSES - 1 alternate a uniform pass (even) and a chain pass
(odd), each timed on the device and counted apart (`measured`); once all are merged it
keeps chains where their visible paths a second are at least MIN_VISIBLE_RATIO times
uniform tracing's (`choice`), the choice and its figures in the job's notes. Passes after
the window that start before the choice are uniform passes. The window is fixed by pass
index (half of it each kind), so the choice is a function of the merged counters, made once.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

# Counters a pass adds, in the kernel's order (kernels/photon_chains.cl, CTR_*).
COUNTERS = ("draws", "visible", "splats", "mutations", "accepted", "started", "boot")  # boot: the starts' draws
THETA_MIN, THETA_MAX = 1e-3, 64.0  # "bounding theta to a large finite range" (dissertation 8.2)
THETA_BIN = math.log(2.0) / 4.0  # the grid of theta: four points an octave
PRIOR_SLOPE = -1.0  # d logit(A) / d log theta assumed until two grid points measure it
LOGIT_CLAMP = 1e-4  # acceptances are taken within [this, 1 - this] in logit
MIN_EVIDENCE = 64  # mutations at a grid point before its acceptance counts
PATHS_PER_ITERATION = 8  # a chain pass runs photons per pass / this many iterations (iterations)
CHAIN_SHARE = 0.05  # chains = this share of the visible paths a pass expects (a chain's start costs 1 / V_c draws)
MIN_CHAINS, MAX_CHAINS = 16, 4096
MIN_BOOT_DRAWS = 256  # a chain's start: at least this many uniform draws, else photons / chains
MEASURE_PASSES = 16  # sampler auto: a job's first passes, the even ones uniform and the odd ones chains (choice)
MEASURED = "measured_"  # prefix of the counters only those passes add (measured)
MEASURED_COUNTERS = ("draws", "visible", "splats", "mutations", "accepted")  # a chain pass's, kept apart
MIN_VISIBLE_RATIO = 20.0  # sampler auto runs chains where their visible paths a second are this many times uniform's


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
    """Chain iterations for a pass whose user asked for `photons` photon paths: photons /
    PATHS_PER_ITERATION. The pass's sums are in uniform photons whatever its iterations
    (pass_scale), so this sets its cost and noise, not its radius schedule."""
    return max(1, photons // PATHS_PER_ITERATION)


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


def runs_chains(pass_index: int, measuring: bool) -> bool:
    """Whether a pass of a batch that runs chains traces its photons with them: every pass,
    or while `measuring` (sampler auto before its choice) the odd ones below MEASURE_PASSES
    (the even ones and those after are uniform passes)."""
    return not measuring or (measures(pass_index) and pass_index % 2 == 1)


def measures(pass_index: int) -> bool:
    """Whether a pass is one that sampler auto measures (and times: measured)."""
    return pass_index < MEASURE_PASSES


def measured(seconds: float, counts: dict[str, int] | None) -> dict[str, int]:
    """The counters a measuring pass adds beside the others: its device time in
    microseconds, and for a chain pass (`counts` its COUNTERS) those of MEASURED_COUNTERS,
    which only these passes add, so that the choice is fixed once they are all merged."""
    kind = "uniform" if counts is None else "chain"
    out = {f"{MEASURED}{kind}_passes": 1, f"{MEASURED}{kind}_us": round(seconds * 1e6)}
    if counts is not None:
        out.update({f"{MEASURED}{name}": counts[name] for name in MEASURED_COUNTERS})
    return out


@dataclass(frozen=True)
class Choice:
    """Sampler auto's choice, from its measuring passes (choice)."""

    chains: bool
    visible_fraction: float  # V_c of the chain passes' uniform draws
    uniform_seconds: float  # device seconds of a uniform pass
    chain_seconds: float  # ... of a chain pass
    acceptance: float  # of the chain passes' mutations
    uniform_rate: float  # visible photon paths a second, uniform: V_c photons / uniform_seconds
    chain_rate: float  # ... chains: splats / chain_seconds

    @property
    def ratio(self) -> float:
        return visible_ratio(self.uniform_rate, self.chain_rate)

    def note(self) -> str:
        """The choice and its figures, one line (the job's notes)."""
        chosen = "chains" if self.chains else "uniform photons"
        return (f"sampler auto: {chosen}: visible paths a second {self.ratio:.3g} times uniform's "
                f"({'at least' if self.chains else 'below'} {MIN_VISIBLE_RATIO:g}), from passes "
                f"0-{MEASURE_PASSES - 1}: V_c {self.visible_fraction:.3g}, a uniform pass {self.uniform_seconds:.3g} s "
                f"({self.uniform_rate:.4g} visible/s), a chain pass {self.chain_seconds:.3g} s "
                f"({self.chain_rate:.4g} visible/s, acceptance {self.acceptance:.3g})")


def choice(counters: dict[str, int], photons: int) -> Choice | None:
    """Sampler auto's choice once all MEASURE_PASSES measuring passes are merged (None
    before): chains iff their visible photon paths a second are at least MIN_VISIBLE_RATIO
    times uniform tracing's, both measured on the scene at hand (device seconds a pass;
    uniform tracing's V_c photons a pass, the chains' splats). A chain's visible paths are
    correlated (a kept state is splatted again, an accepted mutation is near its state),
    uniform tracing's independent; the dissertation states the cost of that correlation
    only through this ratio (8.5: the chains gain nothing where it is below 10, some at
    41.9, "the ratio may need to be more than a few tens"). A function of the merged
    counters alone, which only the measuring passes add to: the same whatever the batch
    split, and fixed once made."""
    if measured_passes(counters) < MEASURE_PASSES:
        return None
    c = {name[len(MEASURED):]: value for name, value in counters.items() if name.startswith(MEASURED)}
    n_uniform, n_chain = c["uniform_passes"], c["chain_passes"]
    draws, visible, splats, mutations, accepted = (c.get(name, 0) for name in MEASURED_COUNTERS)
    v_c = visible / draws if draws else 0.0
    uniform_us, chain_us = max(c.get("uniform_us", 0), 1), max(c.get("chain_us", 0), 1)
    uniform_rate = v_c * photons * n_uniform / (uniform_us * 1e-6)
    chain_rate = splats / (chain_us * 1e-6)
    return Choice(visible_ratio(uniform_rate, chain_rate) >= MIN_VISIBLE_RATIO, v_c,
                  uniform_us * 1e-6 / n_uniform, chain_us * 1e-6 / n_chain,
                  accepted / mutations if mutations else 0.0, uniform_rate, chain_rate)


def visible_ratio(uniform_rate: float, chain_rate: float) -> float:
    """The paper's visible photon ratio, chains over uniform (here at equal time); 0 when
    neither finds a visible path."""
    if uniform_rate > 0.0:
        return chain_rate / uniform_rate
    return math.inf if chain_rate > 0.0 else 0.0


def measured_passes(counters: dict[str, int]) -> int:
    """Measuring passes merged into these counters."""
    return counters.get(f"{MEASURED}uniform_passes", 0) + counters.get(f"{MEASURED}chain_passes", 0)


def measuring_note(counters: dict[str, int]) -> str:
    """What sampler auto says before its choice."""
    return f"sampler auto: measuring ({measured_passes(counters)} of passes 0-{MEASURE_PASSES - 1} merged)"
