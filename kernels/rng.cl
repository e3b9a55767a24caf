// Counter-based random numbers.
//
// A stream is a pure function of (job seed, pass index, stream id, domain): passes are
// statistically independent and reproducible whichever worker runs them, in any order
// (digest 11.1 item 12). The generator is SplitMix64, itself counter-based: output i is
// mix(state0 + i * golden), so there is no hidden sequential state to carry across passes.
// The domains DOMAIN_* come from kernels/contract.py as build options.

typedef struct { ulong state; } Rng;

inline ulong mix64(ulong z) {
    z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9UL;
    z = (z ^ (z >> 27)) * 0x94D049BB133111EBUL;
    return z ^ (z >> 31);
}

inline Rng rng_make(ulong seed, uint pass, uint stream, ulong domain) {
    Rng r;
    r.state = mix64(mix64(seed ^ (domain << 56)) ^ (((ulong)pass << 32) | (ulong)stream));
    return r;
}

inline uint rng_u32(Rng* r) {
    r->state += 0x9E3779B97F4A7C15UL;
    return (uint)(mix64(r->state) >> 32);
}

// Uniform in [0, 1): 24 random bits, so 1.0f is never returned.
inline float rng_float(Rng* r) { return (float)(rng_u32(r) >> 8) * 0x1p-24f; }
