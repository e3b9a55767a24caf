// BSDF queries of the hybrid integrator (vertex connection and merging, Georgiev et al.
// 2012): the value of a surface's BSDF for a given pair of directions with the solid-angle
// pdfs of sampling either direction from the other, and a sampled bounce with those pdfs.
// The MIS weights need both pdfs at every non-specular vertex (the "forward" pdf the path
// used and the "reverse" pdf the opposite subpath would have used).
//
// Diffuse: f = rho / pi, pdf = cos / pi about the shading normal. Glossy (modified Phong
// about the mirror direction, materials.cl): f = rho (e+2)/(2 pi) cos^e(a), pdf =
// (e+1)/(2 pi) cos^e(a), both symmetric in the two directions. Mirror and glass are delta
// (is_delta): they are only ever sampled, and their pdfs cancel in the weights.
// Directions: wo points back along the path that reached the surface, wi the other way;
// both leave the surface.

typedef struct {
    float3 f;       // BSDF value, no cosine (0: the pair is not reflected)
    float pdf_fwd;  // pdf of sampling wi given wo
    float pdf_rev;  // pdf of sampling wo given wi
} BsdfEval;

typedef struct {
    float3 dir;     // the new direction (leaving the surface)
    float3 weight;  // f cos / pdf (the Russian roulette of glass's two branches included)
    float pdf_fwd, pdf_rev;
    bool delta;     // mirror or glass: pdfs undefined, weights use the delta rules
} BsdfSample;

inline bool is_delta(int type) { return type == MAT_MIRROR || type == MAT_GLASS; }

inline BsdfEval bsdf_eval(int type, float param, float3 albedo, float3 ng, float3 ns, float3 wo, float3 wi) {
    BsdfEval e = {(float3)(0.0f), 0.0f, 0.0f};
    float go = dot(wo, ng), gi = dot(wi, ng);
    if (go * gi <= 0.0f || is_delta(type)) return e;  // reflection only, both on one side of the true surface
    float3 n = go > 0.0f ? ns : -ns;
    float co = dot(wo, n), ci = dot(wi, n);
    if (co <= 0.0f || ci <= 0.0f) return e;
    if (type == MAT_DIFFUSE) {
        e.f = albedo / PI_F;
        e.pdf_fwd = ci / PI_F;
        e.pdf_rev = co / PI_F;
        return e;
    }
    float ca = dot(wi, reflect_dir(-wo, n));  // glossy: the angle to the mirror direction
    if (ca <= 0.0f) return e;
    float lobe = pow(ca, param) / (2.0f * PI_F);
    e.f = albedo * ((param + 2.0f) * lobe);
    e.pdf_fwd = e.pdf_rev = (param + 1.0f) * lobe;
    return e;
}

// A bounce of a path arriving along d (propagation direction) at a surface; false if the
// path is absorbed (a glossy sample below the surface, a diffuse one through it).
inline bool bsdf_sample(int type, float param, float3 albedo, float3 ng, float3 ns, float3 d, Rng* rng,
                        BsdfSample* s) {
    s->delta = is_delta(type);
    s->pdf_fwd = s->pdf_rev = 1.0f;
    if (type == MAT_DIFFUSE) {
        float3 n = dot(d, ng) < 0.0f ? ns : -ns;
        s->dir = sample_cosine(n, rng_float(rng), rng_float(rng));
        s->weight = albedo;  // (rho/pi) cos / (cos/pi)
    } else if (!scatter_specular(type, param, albedo, d, ng, ns, rng, &s->dir, &s->weight)) {
        return false;
    }
    if (s->delta) return true;
    BsdfEval e = bsdf_eval(type, param, albedo, ng, ns, -d, s->dir);
    if (e.pdf_fwd <= 0.0f) return false;
    s->pdf_fwd = e.pdf_fwd;
    s->pdf_rev = e.pdf_rev;
    return true;
}
