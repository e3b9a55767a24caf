// Lights in the hybrid integrator: emitting a light subpath, and the pdfs its MIS weights
// need.
//
// Emitter records, selection by power and the light sample (sample_direct, its pdfs): lights.cl.
//
// Initial MIS quantities of a light subpath (VCM tech report, Georgiev 2012, sec. 4),
// p_direct = pick x (position pdf, or 1 for a delta position), p_emit = pick x position pdf
// x direction pdf:  dVCM = p_direct / p_emit,  dVC = cos_l / p_emit (0 for delta lights),
// dVM = dVC / eta_vcm (the caller's). Directional and environment light put no distance
// factor on their first hit (`infinite`), and take cos_l = 1 (SmallVCM's convention for
// lights at infinity).

typedef struct {
    float3 o, d;     // origin (off the emitter's surface) and direction
    float3 flux;     // the subpath's initial throughput: power / pick, as photon_pass.cl
    float dVCM, dVC;
    bool infinite;
} Emission;

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
    } else if (kind == EMIT_DIRECTIONAL) {
        float3 t, b;
        onb(r1.xyz, &t, &b);
        float rr = r1.w * sqrt(u1), phi = 2.0f * PI_F * u2;
        e.o = r0.xyz + rr * (cos(phi) * t + sin(phi) * b);
        e.d = r1.xyz;
        e.dVCM = PI_F * r1.w * r1.w;
        e.infinite = true;
    } else {  // the environment (environment.cl): p_direct = pick pdf(w), p_emit = pick pdf(w) / (pi R^2)
        EnvRay ray = env_emit(emitters, k, u1, u2, u3, u4);
        e.infinite = true;
        e.o = ray.o;
        e.d = ray.d;
        e.flux = ray.flux / r3.w;
        e.dVCM = PI_F * r1.w * r1.w;
        e.dVC = e.dVCM / (r3.w * ray.pdf_w);  // cos_l = 1, as the directional light's
    }
    return e;
}
