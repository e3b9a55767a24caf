// Photon pass: emission proportional to light power, Russian roulette on albedo, a
// photon stored at every hit on a surface with a diffuse part (dissertation 5.3.4; slides
// 3.2; bsdf.cl), except the first hit from the light when direct light comes from
// next-event estimation (`nee`, lights.cl). The path goes on by sampling the whole BSDF.
//
// Emitter records: see lights.cl. Every path counts as one emitted photon, also
// when it misses everything: the estimate is normalised by emitted photons (digest 11.1).
// Each stored photon gets a 64-bit selection key, (random 28 bits << 36) | (path << 12) |
// bounce: a pure function of (seed, pass, path), unique within a pass (path < 2^24 photons
// per pass, bounce < 2^12 = MAX_BOUNCES), so the stochastic hash picks the same photons
// whatever order the atomic slot counter hands out slots in. Ties of the random part are
// broken by (path, bounce); the minimum of n keys is tied with probability under n / 2^28.
// Emitter kinds EMIT_* come from kernels/contract.py as build options.
//
// Paths end by Russian roulette alone (survival = the bounce's largest throughput factor,
// so the expected flux is unchanged); `max_bounces` is only a safety cap, and its lost
// energy is bounded in kernels/contract.py (MAX_BOUNCES).
//
// The path itself is trace_photon, shared with the adaptive sampler (photon_chains.cl):
// where it stores a photon it hands it to a PhotonSink, which either stores it (here) or
// probes it (visibility, and a small cache the chain stores from later). Each stored
// photon carries a count in ph_pos.w (1 here; a chain's state re-counted by rejected
// proposals counts as often as it was splatted), which the exact gather weights by.

typedef struct {
    __global float4* pos;        // xyz position, w: count
    __global float4* flux;       // rgb flux (w: 0)
    __global uint2* dirs;        // packed incoming direction, packed surface normal facing the photon
    __global ulong* key;         // sort and selection key
    __global volatile uint* count;
    uint capacity;
} PhotonStore;

// `n` consecutive slots; the host re-runs the pass with more room when they overflow.
inline uint reserve_photons(const PhotonStore* st, uint n) { return atomic_add(st->count, n); }

inline void write_photon(const PhotonStore* st, uint slot, float3 p, float count, float3 flux, uint2 dirs,
                         ulong key) {
    if (slot >= st->capacity) return;
    // The packed directions keep out of the float lanes: as floats their bits are
    // often denormal, and the vector arithmetic on xyz also runs the w lane.
    st->pos[slot] = (float4)(p, count);
    st->flux[slot] = (float4)(flux, 0.0f);
    st->dirs[slot] = dirs;
    st->key[slot] = key;
}

// A chain photon's key for the stochastic hash: its (record << 12) | bounce with the top 28
// bits replaced by a hash of the low 36 (record mod 2^24, bounce). The hash keeps one photon
// per entry by the smallest key, which must be a random choice among the entry's photons:
// a chain state stored again (photon_chains.cl) gets a new record, so each copy draws anew.
inline ulong salted_key(ulong key) {
    ulong low = key & 0xFFFFFFFFFUL;
    return ((mix64(low ^ 0x5851F42D4C957F2DUL) >> 36) << 36) | low;
}

// Where trace_photon puts its photons: stored at once (SINK_STORE); or probed: judged
// against the measurement points (PointGrid, visibility.cl) and the first DEPOSIT_CACHE
// kept, so an accepted chain state is stored without tracing it again (SINK_PROBE); or
// judged and stored at once (SINK_JUDGE: chains that do not mutate splat every visible
// uniform draw once, and an invisible one's photons are never gathered).
#define SINK_STORE 0
#define SINK_PROBE 1
#define SINK_JUDGE 2

typedef struct {
    PhotonStore store;
    int salted;                  // store keys as salted_key (chains, for the stochastic hash)
    int probe;                   // SINK_*
    PointGrid grid;
    int visible;                 // some photon lands in a measurement point's disc
    int n;                       // photons of the path (also those beyond the cache)
    float4 c_pos[DEPOSIT_CACHE];
    float4 c_flux[DEPOSIT_CACHE];
    uint2 c_dirs[DEPOSIT_CACHE];
    ulong c_key[DEPOSIT_CACHE];
} PhotonSink;

inline void sink_photon(PhotonSink* s, float3 p, float3 flux, uint2 dirs, ulong key) {
    if (s->probe != SINK_STORE && !s->visible) s->visible = photon_visible(&s->grid, p, dirs);
    if (s->probe != SINK_PROBE) {
        write_photon(&s->store, reserve_photons(&s->store, 1), p, 1.0f, flux, dirs, s->salted ? salted_key(key) : key);
        return;
    }
    if (s->n < DEPOSIT_CACHE) {
        s->c_pos[s->n] = (float4)(p, 0.0f);
        s->c_flux[s->n] = (float4)(flux, 0.0f);
        s->c_dirs[s->n] = dirs;
        s->c_key[s->n] = key;
    }
    s->n++;
}

// One photon path from `rng` (a counter stream, or a primary sample vector: rng.cl).
// Keys: with `random_key`, (random 28 bits << 36) | (path << 12) | bounce, as the
// stochastic hash needs; else (path << 12) | bounce, path up to 52 bits.
inline void trace_photon(const SceneGeom* g, __global const float4* surfaces,
                         __global const float4* emitters, __global const float* emitter_cdf, int n_emitters,
                         Rng* rng, int max_bounces, int skip_first_hit, ulong path, int random_key,
                         PhotonSink* sink) {
    // Pick an emitter in proportion to its power.
    int lo = pick_emitter(emitter_cdf, n_emitters, rng_float(rng));
    float4 r0 = emitters[4 * lo], r1 = emitters[4 * lo + 1], r2 = emitters[4 * lo + 2], r3 = emitters[4 * lo + 3];
    float3 flux = r3.xyz / r3.w;
    float u1 = rng_float(rng), u2 = rng_float(rng), u3 = rng_float(rng), u4 = rng_float(rng);
    float3 o, d;
    int kind = as_int(r0.w);
    if (kind == EMIT_TRIANGLE || kind == EMIT_SPHERE) {
        EmitterPoint ep = sample_emitter_point(kind, r0, r1, r2, u1, u2);
        d = sample_cosine(ep.n, u3, u4);
        o = ep.y + ep.n * ray_eps(g, ep.y);
    } else if (kind == EMIT_POINT) {
        o = r0.xyz;
        d = sample_sphere(u1, u2);
    } else if (kind == EMIT_SPOT) {
        o = r0.xyz;
        d = sample_cone(r1.xyz, r1.w, u1, u2);
    } else if (kind == EMIT_DIRECTIONAL) {  // a disc of radius r1.w facing r1.xyz covers the bounding sphere
        float3 t, b;
        onb(r1.xyz, &t, &b);
        float rr = r1.w * sqrt(u1), phi = 2.0f * PI_F * u2;
        o = r0.xyz + rr * (cos(phi) * t + sin(phi) * b);
        d = r1.xyz;
    } else {  // the environment: a direction by its distribution, from its disc (environment.cl)
        EnvRay ray = env_emit(emitters, lo, u1, u2, u3, u4);
        o = ray.o;
        d = ray.d;
        flux = ray.flux / r3.w;
    }

    for (int bounce = 0; bounce < max_bounces; ++bounce) {
        Hit h = intersect(g, o, d);
        if (h.surf == SURF_NONE) return;
        float3 p = o + h.t * d;
        Material m = hit_material(g, surfaces, &h, p);
        if ((material_parts(&m) & PART_DIFFUSE) && (bounce > 0 || !skip_first_hit)) {
            // Stored with the share h(wi) the diffuse part takes of it (bsdf.cl).
            float3 n = dot(d, h.ng) < 0.0f ? h.ng : -h.ng;
            float3 ns = dot(d, h.ng) < 0.0f ? h.ns : -h.ns;
            ulong key = (path << 12) | (ulong)bounce;
            if (random_key) key |= (ulong)(rng_u32(rng) >> 4) << 36;
            float3 stored = (h.smooth ? flux * shading_arrival(d, h.ng, h.ns) : flux) * coat_in(&m, -dot(d, ns));
            sink_photon(sink, p, stored, (uint2)(pack_dir(-d), pack_dir(n)), key);
        }
        BsdfSample b;
        if (!bsdf_sample(&m, h.ng, h.ns, d, PART_ALL, false, rng, &b)) return;
        float3 w = b.weight, nd = b.dir;
        if (h.smooth) w *= shading_bounce(d, nd, h.ng, h.ns, true);
        // Russian roulette on the throughput factor keeps the expected flux unchanged.
        float survive = fmin(1.0f, fmax(w.x, fmax(w.y, w.z)));
        if (rng_float(rng) >= survive) return;
        flux *= w / survive;
        d = nd;
        o = p + (dot(nd, h.ng) > 0.0f ? h.ng : -h.ng) * ray_eps(g, p);
    }
}

__kernel void photon_pass(
    SCENE_PARAMS,
    ulong seed, uint pass, uint n_paths, int max_bounces, uint capacity,
    int skip_first_hit,          // 1: store nothing at a photon's first hit (direct light is NEE's)
    __global float4* ph_pos,     // xyz position, w: count (1)
    __global float4* ph_flux,    // rgb flux (w: 0)
    __global uint2* ph_dirs,     // packed incoming direction, packed surface normal facing the photon
    __global ulong* ph_key,      // selection key for the stochastic hash
    __global volatile uint* ph_count)
{
    uint path = (uint)get_global_id(0);
    if (path >= n_paths || n_emitters == 0) return;
    SceneGeom g = SCENE_GEOM;
    Rng rng = rng_make(seed, pass, path, DOMAIN_PHOTON);
    PhotonSink sink;
    sink.store = (PhotonStore){ph_pos, ph_flux, ph_dirs, ph_key, ph_count, capacity};
    sink.probe = SINK_STORE;
    sink.salted = 0;
    trace_photon(&g, surfaces, emitters, emitter_cdf, n_emitters, &rng, max_bounces, skip_first_hit,
                 (ulong)path, 1, &sink);
}
