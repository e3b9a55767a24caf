// Counter-based random numbers.
//
// A stream is a pure function of (job seed, pass index, stream id, domain): passes are
// statistically independent and reproducible whichever worker runs them, in any order
// (digest 11.1 item 12). The generator is SplitMix64, itself counter-based: output i is
// mix(state0 + i * golden), so there is no hidden sequential state to carry across passes.
// The domains DOMAIN_* come from kernels/contract.py as build options.
//
// Primary sample space (adaptive photon tracing, kernels/photon_chains.cl): a generator
// made by rng_from_sample hands out the `dim` numbers of a given vector u first, in the
// order a path asks for them, and after those a stream seeded by a hash of u; a path is
// then a pure function of u, so a Markov chain can mutate u and re-trace it exactly.

typedef struct {
    ulong state;
    __private const float* u;  // the primary sample vector, or 0
    int dim, next;             // its length, and the next dimension to hand out
} Rng;

inline ulong mix64(ulong z) {
    z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9UL;
    z = (z ^ (z >> 27)) * 0x94D049BB133111EBUL;
    return z ^ (z >> 31);
}

inline Rng rng_make(ulong seed, uint pass, uint stream, ulong domain) {
    Rng r;
    r.state = mix64(mix64(seed ^ (domain << 56)) ^ (((ulong)pass << 32) | (ulong)stream));
    r.u = 0;
    r.dim = r.next = 0;
    return r;
}

inline Rng rng_from_sample(__private const float* u, int dim) {
    Rng r;
    ulong h = 0x243F6A8885A308D3UL;
    for (int k = 0; k < dim; ++k) h = mix64(h ^ (ulong)as_uint(u[k]) ^ ((ulong)k << 32));
    r.state = h;
    r.u = u;
    r.dim = dim;
    r.next = 0;
    return r;
}

inline uint rng_u32(Rng* r) {
    r->state += 0x9E3779B97F4A7C15UL;
    return (uint)(mix64(r->state) >> 32);
}

// Uniform in [0, 1): 24 random bits, so 1.0f is never returned; from a primary sample
// vector, its next dimension while any are left (in [0, 1) too: photon_chains.cl wraps).
inline float rng_float(Rng* r) {
    if (r->next < r->dim) return r->u[r->next++];
    return (float)(rng_u32(r) >> 8) * 0x1p-24f;
}
