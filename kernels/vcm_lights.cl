// Lights in the hybrid integrator: emitting a light subpath, sampling a light from a
// camera vertex (next-event estimation), and the pdfs its MIS weights need.
//
// Emitter records and selection by power: lights.cl. Pdfs here leave out the selection
// probability `pick` where it cancels in a ratio. Per kind, with A the emitter's area:
//   kind         position pdf   direction pdf       direct pdf (NEE)       li (NEE)
//   triangle,    1 / A          cos_l / pi          d^2 / (A cos_l)        Le = P / (pi A)
//   sphere                                          (solid angle)          (radiance)
//   point        delta          1 / (4 pi)          d^2 (delta position)   P / (4 pi) (intensity)
//   spot         delta          1 / (2 pi (1-c))    d^2                    P / (2 pi (1-c))
//   directional  1 / (pi R^2)   delta               1 (delta direction)    P / (pi R^2) (irradiance)
// (directional: a disc of radius R facing the light's direction covers the scene). The
// NEE estimate is then f cos li / (pick direct_pdf) for every kind.
//
// Initial MIS quantities of a light subpath (VCM tech report, Georgiev 2012, sec. 4),
// p_direct = pick x (position pdf, or 1 for a delta position), p_emit = pick x position pdf
// x direction pdf:  dVCM = p_direct / p_emit,  dVC = cos_l / p_emit (0 for delta lights),
// dVM = dVC / eta_vcm (the caller's). Directional light puts no distance factor on its first
// hit (`infinite`).

typedef struct {
    float3 o, d;     // origin (off the emitter's surface) and direction
    float3 flux;     // the subpath's initial throughput: power / pick, as photon_pass.cl
    float dVCM, dVC;
    bool infinite;
} Emission;

typedef struct {
    float3 wi;          // toward the light
    float3 end;         // the shadow ray's end (lights.cl, shadow_end), unless directional
    float3 li;          // see the table
    float pick, direct_pdf, emission_pdf, cos_light;  // emission_pdf: position x direction, no pick
    bool delta;         // point, spot, directional: a BSDF sample never finds it
    bool directional;   // the shadow ray goes on forever
} DirectSample;

inline float total_power(__global const float4* emitters) {
    float4 r3 = emitters[3];  // any record: its power / its probability
    return (r3.x + r3.y + r3.z) / r3.w;
}

inline Emission sample_emission(const SceneGeom* g, __global const float4* emitters, __global const float* cdf,
                                int n_emitters, Rng* rng) {
    int k = pick_emitter(cdf, n_emitters, rng_float(rng));
    float4 r0 = emitters[4 * k], r1 = emitters[4 * k + 1], r2 = emitters[4 * k + 2], r3 = emitters[4 * k + 3];
    float u1 = rng_float(rng), u2 = rng_float(rng), u3 = rng_float(rng), u4 = rng_float(rng);
    Emission e;
    e.flux = r3.xyz / r3.w;
    e.infinite = false;
    e.dVC = 0.0f;
    int kind = as_int(r0.w);
    if (kind == EMIT_TRIANGLE || kind == EMIT_SPHERE) {
        EmitterPoint ep = sample_emitter_point(kind, r0, r1, r2, u1, u2);
        float3 n = ep.n;
        float area = ep.area;
        e.o = ep.y;
        e.d = sample_cosine(n, u3, u4);
        e.o += n * ray_eps(g, e.o);
        float cos_l = fmax(dot(e.d, n), 1e-6f);
        e.dVCM = PI_F / cos_l;                   // (pick / A) / (pick / A cos_l / pi)
        e.dVC = PI_F * area / r3.w;              // cos_l / (pick / A cos_l / pi)
    } else if (kind == EMIT_POINT) {
        e.o = r0.xyz;
        e.d = sample_sphere(u1, u2);
        e.dVCM = 4.0f * PI_F;
    } else if (kind == EMIT_SPOT) {
        e.o = r0.xyz;
        e.d = sample_cone(r1.xyz, r1.w, u1, u2);
        e.dVCM = 2.0f * PI_F * (1.0f - r1.w);
    } else {  // directional
        float3 t, b;
        onb(r1.xyz, &t, &b);
        float rr = r1.w * sqrt(u1), phi = 2.0f * PI_F * u2;
        e.o = r0.xyz + rr * (cos(phi) * t + sin(phi) * b);
        e.d = r1.xyz;
        e.dVCM = PI_F * r1.w * r1.w;
        e.infinite = true;
    }
    return e;
}

// A light sample seen from x; false if the emitter faces away or x is outside a spot's cone.
inline bool sample_direct(const SceneGeom* g, __global const float4* emitters, __global const float* cdf,
                          int n_emitters, float3 x, Rng* rng, DirectSample* s) {
    int k = pick_emitter(cdf, n_emitters, rng_float(rng));
    float4 r0 = emitters[4 * k], r1 = emitters[4 * k + 1], r2 = emitters[4 * k + 2], r3 = emitters[4 * k + 3];
    float u1 = rng_float(rng), u2 = rng_float(rng);
    int kind = as_int(r0.w);
    s->pick = r3.w;
    s->delta = kind != EMIT_TRIANGLE && kind != EMIT_SPHERE;
    s->directional = kind == EMIT_DIRECTIONAL;
    s->cos_light = 1.0f;
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

// Selection times position pdf of the area emitter point a camera path hit, with emission
// Le there: pick / A = (P_k / P) / A = pi sum(Le) / P (Lambertian emitters, lights.cl).
inline float hit_emitter_pdf_area(float3 le, float power) { return PI_F * (le.x + le.y + le.z) / power; }
