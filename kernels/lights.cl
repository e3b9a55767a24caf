// Lights: picking an emitter, and next-event estimation of direct light at a measurement
// point (`direct: nee`, as pbrt-v4's SPPM).
//
// Emitter records are four float4 rows: row0 = (position or v0 or disc centre, type),
// row1 = (edge1 | axis | direction, cos cone | disc radius), row2 = (edge2, sphere radius),
// row3 = (power rgb, selection probability), chosen in proportion to power (summed rgb;
// worker/scene_arrays.py). Area emitters (triangles, spheres) are Lambertian, shining from
// their front side with radiance Le = power / (pi area).
//
// The light sample (sample_direct), shared by SPPM's next-event estimation and the hybrid
// integrator's, whose MIS weights (vcm_lights.cl, vcm_camera_pass.cl) also need the pdf
// of emitting toward x. Pdfs leave out the selection probability `pick`. Per kind, with A
// the emitter's area:
//   kind         position pdf   direction pdf       direct pdf (NEE)       li (NEE)
//   triangle,    1 / A          cos_l / pi          d^2 / (A cos_l)        Le = P / (pi A)
//   sphere                                          (solid angle)          (radiance)
//   point        delta          1 / (4 pi)          d^2 (delta position)   P / (4 pi) (intensity)
//   spot         delta          1 / (2 pi (1-c))    d^2                    P / (2 pi (1-c))
//   directional  1 / (pi R^2)   delta               1 (delta direction)    P / (pi R^2) (irradiance)
//   environment  1 / (pi R^2)   pdf(w)              pdf(w) (solid angle)   L(w) (radiance)
// (directional, environment: a disc of radius R facing the light's direction covers the
// scene; environment.cl). The NEE estimate is then f cos li / (pick direct_pdf) for every kind.
//
// Direct light at a measurement point x through its diffuse part (f = g h(wi) / pi,
// bsdf.cl) is estimated per pass by one light sample and one cosine-weighted BSDF sample. Delta lights (point, spot,
// directional) give L f cos / p with no MIS (a BSDF sample never hits them); area lights
// and the environment are weighted by the power heuristic between the two techniques,
// whose pdfs in solid angle at x are
//     p_light = P_k / P * d^2 / (A_k cos_l) = pi sum(Le) d^2 / (P cos_l)  (area)
//     p_light = pick pdf(w)                                                (environment)
//     p_bsdf  = cos_s / pi
// (P_k = pi sum(Le) A_k the emitter's power, P the total: the light pdf of a direction
// needs only the emission of the surface it hits; a direction that leaves the scene finds
// the environment: env_escape). The photon pass then stores nothing at
// a photon's first hit, so direct light is counted once, while light reaching x through
// specular surfaces (caustics) stays with the photons: a shadow ray stops at glass. At a
// glossy vertex of an eye path (light_sample_parts) one light sample is weighted the same
// way against the path's own next bounce, whose emission hit the eye pass weights by
// emission_weight.

// Index of the emitter whose CDF interval holds u.
inline int pick_emitter(__global const float* cdf, int n, float u) { return cdf_search(cdf, n, u); }

// A uniform point on an area emitter (a triangle or sphere record, rows r0..r2), its
// outward normal and the emitter's area, from two uniform numbers: what the light sample,
// the photon pass and the hybrid integrator's light subpaths all start from.
typedef struct { float3 y, n; float area; } EmitterPoint;

inline EmitterPoint sample_emitter_point(int kind, float4 r0, float4 r1, float4 r2, float u1, float u2) {
    EmitterPoint p;
    if (kind == EMIT_TRIANGLE) {
        float su = sqrt(u1);
        p.y = r0.xyz + (1.0f - su) * r1.xyz + u2 * su * r2.xyz;
        float3 c = cross(r1.xyz, r2.xyz);
        p.area = 0.5f * length(c);
        p.n = normalize(c);
    } else {
        p.n = sample_sphere(u1, u2);
        p.y = r0.xyz + r2.w * p.n;
        p.area = 4.0f * PI_F * r2.w * r2.w;
    }
    return p;
}

inline float power_heuristic(float a, float b) { return a * a / (a * a + b * b); }

// Where a shadow ray toward the light point y ends: off y along n, y's normal on the side that
// faces the shaded point, as every ray leaves a surface (geometry.cl, blocked_between). A
// point light takes the direction back to the shaded point, in case it sits on a surface.
inline float3 shadow_end(const SceneGeom* g, float3 y, float3 n) { return y + n * ray_eps(g, y); }

// A light sample seen from a point x.
typedef struct {
    float3 wi;          // toward the light
    float3 end;         // the shadow ray's end (shadow_end), unless directional
    float3 li;          // the table above
    float pick, direct_pdf, emission_pdf, cos_light;  // emission_pdf: position x direction, no pick
    bool delta;         // point, spot, directional: a BSDF sample never finds it
    bool directional;   // the shadow ray goes on forever (directional, environment)
} DirectSample;

// The emitters' total power P.
inline float total_power(__global const float4* emitters) {
    float4 r3 = emitters[3];  // any record: its power / its probability
    return (r3.x + r3.y + r3.z) / r3.w;
}

// A light sample seen from x; false if the emitter faces away or x is outside a spot's cone.
inline bool sample_direct(const SceneGeom* g, __global const float4* emitters, __global const float* cdf,
                          int n_emitters, float3 x, Rng* rng, DirectSample* s) {
    int k = pick_emitter(cdf, n_emitters, rng_float(rng));
    float4 r0 = emitters[4 * k], r1 = emitters[4 * k + 1], r2 = emitters[4 * k + 2], r3 = emitters[4 * k + 3];
    float u1 = rng_float(rng), u2 = rng_float(rng);
    int kind = as_int(r0.w);
    s->pick = r3.w;
    s->delta = kind != EMIT_TRIANGLE && kind != EMIT_SPHERE && kind != EMIT_ENVIRONMENT;
    s->directional = kind == EMIT_DIRECTIONAL || kind == EMIT_ENVIRONMENT;
    s->cos_light = 1.0f;
    if (kind == EMIT_ENVIRONMENT) {
        s->wi = env_sample(emitters, k, u1, u2, &s->direct_pdf);
        if (s->direct_pdf <= 0.0f) return false;
        s->li = env_radiance(emitters, k, s->wi);
        s->emission_pdf = s->direct_pdf / (PI_F * r1.w * r1.w);
        return true;
    }
    if (!s->delta) {
        EmitterPoint ep = sample_emitter_point(kind, r0, r1, r2, u1, u2);
        float3 y = ep.y, nl = ep.n;
        float area = ep.area;
        float3 to = y - x;
        float d2 = dot(to, to);
        s->wi = to / sqrt(d2);
        s->cos_light = -dot(s->wi, nl);
        if (s->cos_light <= 0.0f || area <= 0.0f) return false;
        s->li = r3.xyz / (PI_F * area);  // Le = P_k / (pi A)
        s->direct_pdf = d2 / (area * s->cos_light);
        s->emission_pdf = s->cos_light / (PI_F * area);
        s->end = shadow_end(g, y, nl);
        return true;
    }
    if (kind == EMIT_DIRECTIONAL) {
        s->wi = -r1.xyz;
        s->li = r3.xyz / (PI_F * r1.w * r1.w);
        s->direct_pdf = 1.0f;
        s->emission_pdf = 1.0f / (PI_F * r1.w * r1.w);
        return true;
    }
    float3 to = r0.xyz - x;
    float d2 = dot(to, to);
    s->wi = to / sqrt(d2);
    s->end = shadow_end(g, r0.xyz, -s->wi);
    s->direct_pdf = d2;
    if (kind == EMIT_POINT) {
        s->emission_pdf = 1.0f / (4.0f * PI_F);
    } else {
        if (-dot(s->wi, r1.xyz) < r1.w) return false;  // outside the cone
        s->emission_pdf = 1.0f / (2.0f * PI_F * (1.0f - r1.w));
    }
    s->li = r3.xyz * s->emission_pdf;  // intensity
    return true;
}

// Whether the shadow ray of light sample `s` from o (off the shaded surface) is blocked.
inline bool shadowed(const SceneGeom* g, float3 o, const DirectSample* s) {
    return s->directional ? occluded(g, o, s->wi, INFINITY) : blocked_between(g, o, s->end);
}

// Selection times position pdf of the area emitter point a camera path hit, with emission
// Le there: pick / A = (P_k / P) / A = pi sum(Le) / P (Lambertian emitters).
inline float hit_emitter_pdf_area(float3 le, float power) { return PI_F * (le.x + le.y + le.z) / power; }

// The MIS weight of emission le that a BSDF-sampled direction of pdf `pdf_bsdf` (solid angle)
// found at distance t, arriving at cos_l to the emitter (power heuristic against the light
// sample: sample_light, light_sample_parts).
inline float emission_weight(float3 le, float total, float pdf_bsdf, float t, float cos_l) {
    float p_light = hit_emitter_pdf_area(le, total) * t * t / cos_l;
    return power_heuristic(pdf_bsdf, p_light);
}

// The light sample for the diffuse part f_d = g h(wi) / pi of material m (bsdf.cl; `gw` is g
// with the caller's weights): MIS-weighted f cos li / (pick direct_pdf) from one emitter
// chosen by power, or 0 if the emitter is occluded, behind x, or faces away. n: geometric
// normal on the eye's side; ns: shading normal on that side.
inline float3 sample_light(const SceneGeom* g, __global const float4* emitters, __global const float* cdf,
                           int n_emitters, float3 x, float3 n, float3 ns, float3 gw, const Material* m, Rng* rng) {
    DirectSample s;
    if (!sample_direct(g, emitters, cdf, n_emitters, x, rng, &s)) return (float3)(0.0f);
    float cos_s = dot(s.wi, ns);
    if (cos_s <= 0.0f || dot(s.wi, n) <= 0.0f || shadowed(g, x + n * ray_eps(g, x), &s)) return (float3)(0.0f);
    float pdf = s.pick * s.direct_pdf;
    float mis = s.delta ? 1.0f : power_heuristic(pdf, cos_s / PI_F);
    return gw * coat_in(m, cos_s) / PI_F * s.li * (cos_s * mis / pdf);
}

// The BSDF sample: a cosine-weighted ray from x that collects the emission it hits (or the
// environment's, if it leaves the scene), weighted by the power heuristic against
// sample_light (the only light it can find).
inline float3 sample_bsdf_emission(const SceneGeom* g, __global const float4* surfaces,
                                   __global const float4* emitters, int n_emitters, float3 x, float3 n, float3 ns,
                                   float3 gw, const Material* m, Rng* rng) {
    float3 wi = sample_cosine(ns, rng_float(rng), rng_float(rng));
    if (dot(wi, n) <= 0.0f) return (float3)(0.0f);
    Hit h = intersect(g, x + n * ray_eps(g, x), wi);
    float cos_s = dot(wi, ns);
    if (h.surf == SURF_NONE) {
        float p_light;
        float3 le = env_escape(emitters, n_emitters, wi, &p_light);
        return p_light > 0.0f ? gw * coat_in(m, cos_s) * le * power_heuristic(cos_s / PI_F, p_light) : (float3)(0.0f);
    }
    if (dot(wi, h.ng) >= 0.0f) return (float3)(0.0f);  // emitters shine to their front
    float3 le = surface_emission(surfaces, h.surf);
    float sum_le = le.x + le.y + le.z;
    if (sum_le <= 0.0f) return (float3)(0.0f);
    return gw * coat_in(m, cos_s) * le * emission_weight(le, total_power(emitters), cos_s / PI_F, h.t,
                                                         -dot(wi, h.ng));
}

// Direct light at x through the diffuse part, by both samples (0 in a scene without emitters).
inline float3 direct_light(const SceneGeom* g, __global const float4* surfaces, __global const float4* emitters,
                           __global const float* cdf, int n_emitters, float3 x, float3 n, float3 ns, float3 gw,
                           const Material* m, Rng* rng) {
    if (n_emitters == 0) return (float3)(0.0f);
    return sample_light(g, emitters, cdf, n_emitters, x, n, ns, gw, m, rng)
         + sample_bsdf_emission(g, surfaces, emitters, n_emitters, x, n, ns, gw, m, rng);
}

// Direct light at x through the parts `mask` of m by one light sample, MIS-weighted (power
// heuristic) against the path's own BSDF sample, whose emission hit the caller weights by
// emission_weight (env_escape's p_light if the path leaves the scene). ng: the geometric normal as the shape defines it.
inline float3 light_sample_parts(const SceneGeom* g, __global const float4* emitters, __global const float* cdf,
                                 int n_emitters, const Material* m, float3 x, float3 ng, float3 ns, float3 wo,
                                 int mask, bool radiance, Rng* rng) {
    DirectSample s;
    if (n_emitters == 0 || !sample_direct(g, emitters, cdf, n_emitters, x, rng, &s)) return (float3)(0.0f);
    BsdfEval e = bsdf_eval(m, ng, ns, wo, s.wi, mask, radiance);
    if (e.pdf_fwd <= 0.0f) return (float3)(0.0f);
    float3 side = dot(s.wi, ng) > 0.0f ? ng : -ng;
    if (shadowed(g, x + side * ray_eps(g, x), &s)) return (float3)(0.0f);
    float pdf = s.pick * s.direct_pdf;
    float mis = s.delta ? 1.0f : power_heuristic(pdf, e.pdf_fwd);
    return e.f * s.li * (fabs(dot(s.wi, ns)) * mis / pdf);
}

