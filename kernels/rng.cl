// Counter-based random numbers.
//
// A stream is a pure function of (job seed, pass index, stream id, domain): passes are
// statistically independent and reproducible whichever worker runs them, in any order
// (digest 11.1 item 12). The generator is SplitMix64, itself counter-based: output i is
// mix(state0 + i * golden), so there is no hidden sequential state to carry across passes.
// The domains DOMAIN_* come from kernels/contract.py as build options.
//
// Primary sample space (adaptive photon tracing, kernels/photon_chains.cl): a path is a
// pure function of a vector u of `dim` numbers, handed out first in the order the path
// asks for them, and of a `tail` seed whose stream hands out the numbers after those; so
// a Markov chain can mutate u and re-trace a state exactly. A proposal is lazy: its
// dimension k is made when the path first asks for it (a path of a few bounces asks for
// far fewer than PSS_DIM), from a counter key `fresh` (SplitMix64 is random access:
// number k is mix(fresh + (k + 1) * golden)), as a fresh uniform number (a uniform draw)
// or as the current state's u[k] plus a mutation step (eq. 9). Only a proposal the chain
// keeps is made whole (rng_sample_fill), with exactly the numbers its path saw.

#define SAMPLE_STREAM 0    // no sample vector: every number from the counter stream
#define SAMPLE_REPLAY 1    // a stored vector u
#define SAMPLE_UNIFORM 2   // a uniform draw, made lazily from `fresh`
#define SAMPLE_MUTATION 3  // u + du, du made lazily from `fresh` and `power`

typedef struct {
    ulong state;
    __private const float* u;  // the stored vector (replay), or the state a mutation starts from
    ulong fresh;               // a lazy proposal's counter key
    float power;               // mutation exponent 1 / theta + 1
    int mode, dim, next;       // SAMPLE_*, the vector's length, the next dimension to hand out
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
    r.fresh = 0;
    r.power = 0.0f;
    r.mode = SAMPLE_STREAM;
    r.dim = r.next = 0;
    return r;
}

// A path's numbers: the first `dim` by `mode` (from u, fresh, power), then `tail`'s stream.
inline Rng rng_sample(int mode, __private const float* u, ulong fresh, float power, ulong tail, int dim) {
    Rng r;
    r.state = tail;
    r.u = u;
    r.fresh = fresh;
    r.power = power;
    r.mode = mode;
    r.dim = dim;
    r.next = 0;
    return r;
}

// x^p for x in [0, 1) and p >= 1, as exp2(p log2 x) with the exponent taken from the
// float's bits and fitted polynomials for the rest (relative error about 1e-6 p): the
// mutation's step length (eq. 9) needs no more (any step length law that does not depend
// on the state keeps the mutation symmetric), and PoCL's pow, or its exp2 and log2, are
// out-of-line library calls, made for every dimension the path asks for.
inline float pow_unit(float x, float p) {
    if (x <= 0.0f) return 0.0f;
    uint bits = as_uint(x);
    float m = as_float((bits & 0x007FFFFFu) | 0x3F800000u) - 1.0f;  // mantissa - 1, in [0, 1)
    float lg = (float)((int)(bits >> 23) - 127) +
               m * (1.442693257f + m * (-0.721162734f + m * (0.477705927f + m * (-0.339247762f +
               m * (0.215588514f + m * (-0.096066234f + m * 0.020490341f))))));
    float y = p * lg;  // <= 0
    if (y < -126.0f) return 0.0f;
    float fi = floor(y), f = y - fi;  // f in [0, 1)
    float e = 0.999999896f + f * (0.69315462f + f * (0.24014077f + f * (0.055863283f + f * (0.008946215f +
              f * 0.001895107f))));
    return e * as_float((uint)((int)fi + 127) << 23);
}

// Dimension k of a sample vector, in [0, 1).
__attribute__((noinline)) float rng_sample_dim(const Rng* r, int k) {
    if (r->mode == SAMPLE_REPLAY) return r->u[k];
    ulong z = mix64(r->fresh + (ulong)(k + 1) * 0x9E3779B97F4A7C15UL);
    if (r->mode == SAMPLE_UNIFORM) return (float)((uint)(z >> 32) >> 8) * 0x1p-24f;
    // Eq. 9: du = sign(2 xi0 - 1) xi1^(1/theta + 1), xi1 from 24 bits and the sign from another.
    float du = pow_unit((float)((uint)(z >> 40)) * 0x1p-24f, r->power);
    float t = r->u[k] + ((z & 1UL) ? du : -du);
    t -= floor(t);
    return t < 1.0f ? t : 0.0f;  // t - floor(t) can round up to exactly 1
}

// The whole vector a lazy proposal stands for: the numbers its path saw, and the rest.
inline void rng_sample_fill(const Rng* r, __private float* out) {
    for (int k = 0; k < r->dim; ++k) out[k] = rng_sample_dim(r, k);
}

inline uint rng_u32(Rng* r) {
    r->state += 0x9E3779B97F4A7C15UL;
    return (uint)(mix64(r->state) >> 32);
}

inline ulong rng_u64(Rng* r) {
    r->state += 0x9E3779B97F4A7C15UL;
    return mix64(r->state);
}

// Uniform in [0, 1): 24 random bits, so 1.0f is never returned; from a sample vector, its
// next dimension while any are left (in [0, 1) too).
inline float rng_float(Rng* r) {
    if (r->next < r->dim) return rng_sample_dim(r, r->next++);
    return (float)(rng_u32(r) >> 8) * 0x1p-24f;
}
