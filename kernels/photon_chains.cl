// Adaptive photon tracing with photon path visibility (Hachisuka & Jensen 2011; dissertation
// ch. 8), as many parallel Markov chains, one per work item.
//
// A path is a point u of the primary sample space [0,1)^PSS_DIM: every random number of
// the path, in the order trace_photon asks for them (the ones beyond PSS_DIM come from the
// stream of the state's `tail` seed, rng.cl). Proposals are lazy: a path makes only the
// dimensions it asks for, and only a kept proposal is made whole. The target is F(u) = V(u) / V_c, V the path's
// visibility (visibility.cl). Per iteration a chain draws a uniform u_I (replica exchange
// with the uniform sampler, acceptance V(u_I), eq. 4): if visible it replaces the state;
// otherwise the state is mutated, u + du per dimension with du = sign(2 xi0 - 1) xi1^(1/theta
// + 1) wrapped into [0,1) (eq. 9), and the candidate is accepted iff visible (eq. 10). Then
// the state is splatted: a new state's photons are stored with count 1, a state kept again
// adds 1 to the counts of its stored photons instead of being traced again (a rejected
// proposal costs its own trace and nothing for the state) (with the
// stochastic hash it stores them again from its cache; a state with more than
// DEPOSIT_CACHE photons is traced and stored again). Chains that do not mutate
// (worker/adaptive.py, mutates) store each uniform draw's photons as it is traced; they
// are a sample of draws judged for V_c, and the host then traces the pass's photons with
// the uniform kernel over them.
//
// Each chain starts the pass from an exact sample of F: uniform draws until one is visible
// (rejection sampling), at most `boot_cap` (these draws are not counted toward V_c: their
// number depends on what they found). A chain that finds none has no state: until one of
// its main loop's uniform draws is visible it splats nothing (its draws still count toward
// V_c), which keeps every splat an exact sample of F; with nothing visible at all the pass
// is uniform tracing that found nothing. After the pass, scale_pass multiplies its photons'
// counts by photons per pass * V_k / splats (V_k = visible / draws of the pass: the counters
// below), so that its sums are in uniform photons (worker/adaptive.py, pass_scale).
// theta is frozen for the pass (adapted between passes on the host, worker/adaptive.py).
// Stored photons' keys are (record << 12) | bounce, record = chain * (iterations / chains
// + 1) + the iteration that stored them: unique in the pass, so the exact gather's sort
// by key makes the sums the same from run to run (salted for the stochastic hash,
// photon_pass.cl).

// Counters a pass adds (uint, one slot each; worker/adaptive.py names them).
#define CTR_DRAWS 0      // uniform draws of the main loop (I)
#define CTR_VISIBLE 1    // ... of which visible (U)
#define CTR_SPLATS 2     // states splatted (samples of F)
#define CTR_MUTATIONS 3
#define CTR_ACCEPTED 4
#define CTR_STARTED 5    // chains that found a visible start
#define CTR_BOOT 6       // uniform draws of the starts (traced, not counted toward V_c)

typedef struct {
    float u[PSS_DIM];
    ulong tail;          // the seed of the path's numbers after u (rng.cl)
    PhotonSink sink;     // the probe of the path: visibility, and its photons
    uint first;          // first stored slot (when stored and cached)
    int stored;
} ChainState;

// A uniform draw, and a mutation of `from` (eq. 9 on every dimension, wrapped into [0,1)):
// lazy proposals (rng.cl), each dimension made when the path asks for it.
inline Rng uniform_proposal(Rng* rng) {
    ulong fresh = rng_u64(rng);
    return rng_sample(SAMPLE_UNIFORM, 0, fresh, 0.0f, rng_u64(rng), PSS_DIM);
}

inline Rng mutation_proposal(Rng* rng, const ChainState* from, float theta) {
    ulong fresh = rng_u64(rng);
    return rng_sample(SAMPLE_MUTATION, from->u, fresh, 1.0f / theta + 1.0f, rng_u64(rng), PSS_DIM);
}

// The state becomes the proposal it was probed with: its whole vector and its tail.
inline void keep(ChainState* s, const Rng* proposal) {
    rng_sample_fill(proposal, s->u);
    s->tail = proposal->state;
}

typedef struct {
    const SceneGeom* g;
    __global const float4* surfaces;
    __global const float4* emitters;
    __global const float* emitter_cdf;
    int n_emitters, max_bounces, skip_first_hit;
} Tracer;

// Trace a path (a copy of `path`: the proposal stays as it was made) into the state's
// sink, `mode` SINK_PROBE (its visibility and cached photons) or SINK_JUDGE (its
// visibility, its photons stored at once).
inline void probe(const Tracer* t, ChainState* s, Rng path, ulong record, int mode) {
    s->sink.visible = 0;
    s->sink.n = 0;
    s->sink.probe = mode;
    s->stored = 0;
    Rng rng = path;
    trace_photon(t->g, t->surfaces, t->emitters, t->emitter_cdf, t->n_emitters, &rng, t->max_bounces,
                 t->skip_first_hit, record, 0, &s->sink);
}

// Store a cached state's photons (count 1) as record `record`.
inline void store_cached(ChainState* s, ulong record) {
    int n = s->sink.n;
    s->first = reserve_photons(&s->sink.store, (uint)n);
    for (int j = 0; j < n; ++j) {
        ulong key = (record << 12) | (s->sink.c_key[j] & 0xFFFUL);
        write_photon(&s->sink.store, s->first + j, s->sink.c_pos[j].xyz, 1.0f, s->sink.c_flux[j].xyz,
                     s->sink.c_dirs[j], s->sink.salted ? salted_key(key) : key);
    }
    s->stored = 1;
}

// Count the state once more, as record `record`: with `in_place` (the exact gather, which
// weights a photon by its count) add 1 to the counts of its stored photons; else (the
// stochastic hash counts photons, not counts) store them again. A state with too many
// photons to cache is traced again and stored.
inline void splat_state(const Tracer* t, ChainState* s, ulong record, int in_place) {
    if (s->sink.n <= DEPOSIT_CACHE) {
        if (!s->stored || !in_place) {
            store_cached(s, record);
            return;
        }
        for (int j = 0; j < s->sink.n; ++j) {
            uint slot = s->first + (uint)j;
            if (slot < s->sink.store.capacity) s->sink.store.pos[slot].w += 1.0f;
        }
        return;
    }
    PhotonSink writer = s->sink;
    writer.probe = SINK_STORE;
    Rng rng = rng_sample(SAMPLE_REPLAY, s->u, 0, 0.0f, s->tail, PSS_DIM);
    trace_photon(t->g, t->surfaces, t->emitters, t->emitter_cdf, t->n_emitters, &rng, t->max_bounces,
                 t->skip_first_hit, record, 0, &writer);
}

__kernel void photon_chains(
    SCENE_PARAMS,
    ulong seed, uint pass, int max_bounces, uint capacity, int skip_first_hit,
    uint n_chains, uint iterations,   // the pass's photon paths: `iterations` split over the chains
    float theta, uint boot_cap,
    int exchange,                     // 0: no replica exchange once a chain has a state (an ablation, for tests)
    int mutating,                     // 0: no chain, uniform draws splatted iff visible (worker/adaptive.py mutates)
    int in_place,                     // 1: re-count kept states in place (exact gather); 0: store them again
    __global const float4* mp_pos, __global const float4* mp_nrm, __global const uint4* mp_cut,
    __global const float* radius,
    float inv_cell, uint mask, __global const uint* cell_start, __global const uint* cell_count,
    __global const uint* sorted,
    __global float4* ph_pos, __global float4* ph_flux, __global uint2* ph_dirs, __global ulong* ph_key,
    __global volatile uint* ph_count,
    __global volatile uint* counters)
{
    uint chain = (uint)get_global_id(0);
    if (chain >= n_chains || n_emitters == 0) return;
    SceneGeom g = SCENE_GEOM;
    Tracer tracer = {&g, surfaces, emitters, emitter_cdf, n_emitters, max_bounces, skip_first_hit};
    Rng rng = rng_make(seed, pass, chain, DOMAIN_CHAIN);
    uint per = iterations / n_chains, iters = per + (chain < iterations % n_chains ? 1u : 0u);
    ulong record0 = (ulong)chain * (ulong)(per + 1u);  // + the iteration: the photons' record

    // Two states, the chain's and the proposal's, sharing the store and the point grid.
    ChainState states[2];
    for (int k = 0; k < 2; ++k) {
        states[k].sink.store = (PhotonStore){ph_pos, ph_flux, ph_dirs, ph_key, ph_count, capacity};
        states[k].sink.salted = !in_place;
        states[k].sink.grid = (PointGrid){mp_pos, mp_nrm, mp_cut, radius, cell_start, cell_count, sorted, inv_cell, mask};
    }
    int cur = 0, has_state = 0;
    uint draws = 0, visible = 0, splats = 0, mutations = 0, accepted = 0;

    // Start: an exact sample of F by rejection (uniform draws until visible, capped).
    uint boot = 0;
    while (mutating && boot < boot_cap && !has_state) {
        Rng draw = uniform_proposal(&rng);
        probe(&tracer, &states[cur], draw, record0, SINK_PROBE);
        has_state = states[cur].sink.visible;
        if (has_state) keep(&states[cur], &draw);
        ++boot;
    }
    int started = has_state;
    // Without mutations every visible draw is splatted once, as it is traced: its photons
    // are stored at once (an invisible draw's too, which no point gathers), no cache.
    int judge = !mutating && exchange;

    for (uint i = 0; i < iters; ++i) {
        ulong record = record0 + i;
        ChainState* next = &states[1 - cur];
        // Replica exchange with the uniform sampler: a visible uniform path replaces the state.
        Rng proposal = uniform_proposal(&rng);
        probe(&tracer, next, proposal, record, judge ? SINK_JUDGE : SINK_PROBE);
        ++draws;
        visible += next->sink.visible;
        int moved = next->sink.visible && (exchange || !has_state);
        if (!moved && has_state && mutating) {
            // Otherwise mutate the state; the candidate is accepted iff visible.
            proposal = mutation_proposal(&rng, &states[cur], theta);
            probe(&tracer, next, proposal, record, SINK_PROBE);
            ++mutations;
            moved = next->sink.visible;
            accepted += moved;
        }
        if (moved) {
            // Made whole only if it can be traced again: mutated, or replayed to store it.
            if (mutating || (!judge && next->sink.n > DEPOSIT_CACHE)) keep(next, &proposal);
            cur = 1 - cur;
            has_state = 1;
        }
        if (has_state && (moved || mutating)) {  // without mutations a state is splatted once
            if (!judge) splat_state(&tracer, &states[cur], record, in_place);
            ++splats;
        }
    }
    atomic_add(&counters[CTR_DRAWS], draws);
    atomic_add(&counters[CTR_VISIBLE], visible);
    atomic_add(&counters[CTR_SPLATS], splats);
    atomic_add(&counters[CTR_MUTATIONS], mutations);
    atomic_add(&counters[CTR_ACCEPTED], accepted);
    atomic_add(&counters[CTR_STARTED], (uint)started);
    atomic_add(&counters[CTR_BOOT], boot);
}

// A chain pass's photons in uniform photons: every stored photon's count (ph_pos.w, which
// both gathers weigh its flux and the radius rule's count by) times `scale` = photons per
// pass * V_k / splats of the pass (worker/adaptive.py, pass_scale).
__kernel void scale_pass(uint n, float scale, __global float4* ph_pos) {
    uint i = (uint)get_global_id(0);
    if (i < n) ph_pos[i].w *= scale;
}
