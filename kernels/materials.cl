// Materials: the surface records, and the pieces every BSDF is built from (frames, Fresnel
// terms, microfacet distributions). The BSDFs themselves: bsdf.cl.
//
// A surface is SURF_ROWS float4 rows (worker/scene_arrays.py, surface_records):
//   row 0: base colour (diffuse: albedo; plastics: the diffuse base; conductors: specular
//          reflectance; dielectrics: reflection tint; glossy: albedo), w: type MAT_* (int bits)
//   row 1: emission rgb (radiance from the front side), w: roughness alpha (rough_*), Phong
//          exponent (glossy)
//   row 2: conductors: eta rgb; dielectrics: (ior, 0, 0); plastics: (ior, internal diffuse
//          reflectance R_int, specular sampling weight); w: MF_* flags (int bits)
//   row 3: conductors: k rgb; dielectrics: transmission tint; plastics: specular
//          reflectance; w: rough_plastic's row of its transmittance table (int bits)
//   row 4: the textures (textures.cl) of row 0's colour, row 3's colour, the roughness and
//          the opacity, -1 where it is constant (int bits); read only under MF_TEXTURED
//   row 5: x: the opacity (Mitsuba 3's mask: the share of the surface that is there, the rest
//          passes light straight through); read only under MF_MASKED
// ior is interior / exterior. Tables follow the records in the same buffer: TABLE_SIZE
// floats over cos in [0, 1], 4 to a row.
// The type codes MAT_* and flags MF_* come from kernels/contract.py as build options.

#define PI_F 3.14159265358979f

inline void onb(float3 n, float3* t, float3* b) {
    // Duff et al. 2017, "Building an Orthonormal Basis, Revisited".
    float s = n.z >= 0.0f ? 1.0f : -1.0f;
    float a = -1.0f / (s + n.z);
    float c = n.x * n.y * a;
    *t = (float3)(1.0f + s * n.x * n.x * a, s * c, -s * n.x);
    *b = (float3)(c, s + n.y * n.y * a, -n.y);
}

inline float3 from_local(float3 n, float x, float y, float z) {
    float3 t, b;
    onb(n, &t, &b);
    return normalize(x * t + y * b + z * n);
}

// Cosine-weighted direction about n: pdf cos/pi.
inline float3 sample_cosine(float3 n, float u1, float u2) {
    float r = sqrt(u1), phi = 2.0f * PI_F * u2;
    return from_local(n, r * cos(phi), r * sin(phi), sqrt(fmax(0.0f, 1.0f - u1)));
}

inline float3 sample_sphere(float u1, float u2) {
    float z = 1.0f - 2.0f * u1, r = sqrt(fmax(0.0f, 1.0f - z * z)), phi = 2.0f * PI_F * u2;
    return (float3)(r * cos(phi), r * sin(phi), z);
}

// Direction inside the cone of half-angle acos(cos_max) about `axis`, uniform in solid angle.
inline float3 sample_cone(float3 axis, float cos_max, float u1, float u2) {
    float c = 1.0f - u1 * (1.0f - cos_max), s = sqrt(fmax(0.0f, 1.0f - c * c)), phi = 2.0f * PI_F * u2;
    return from_local(axis, s * cos(phi), s * sin(phi), c);
}

inline float3 reflect_dir(float3 d, float3 n) { return d - 2.0f * dot(d, n) * n; }

typedef struct {
    int type;
    uint flags;     // MF_*
    float3 base;    // row 0
    float rough;    // alpha or Phong exponent
    float3 eta;     // row 2
    float3 second;  // row 3
    __global const float* table;  // rough_plastic's coat transmittance table (TABLE_SIZE floats)
    float opacity;  // row 5 (1: opaque)
} Material;

inline Material load_material(__global const float4* surfaces, int surf) {
    __global const float4* r = surfaces + SURF_ROWS * surf;
    float4 r0 = r[0], r2 = r[2], r3 = r[3];
    uint flags = as_uint(r2.w);
    Material m = {as_int(r0.w), flags, r0.xyz, r[1].w, r2.xyz, r3.xyz,
                  (__global const float*)(surfaces + as_int(r3.w)), (flags & MF_MASKED) ? r[5].x : 1.0f};
    return m;
}

inline float3 surface_emission(__global const float4* surfaces, int surf) { return surfaces[SURF_ROWS * surf + 1].xyz; }

// Fresnel reflectance of an unpolarised wave meeting a dielectric interface from the side
// where the relative index (far side / this side) is eta, at cos_i > 0; `cos_t` gets the
// refracted cosine (0 under total internal reflection, where the reflectance is 1).
inline float fresnel_dielectric(float cos_i, float eta, float* cos_t) {
    float sin2_t = (1.0f - cos_i * cos_i) / (eta * eta);
    if (sin2_t >= 1.0f) {
        *cos_t = 0.0f;
        return 1.0f;
    }
    float ct = sqrt(1.0f - sin2_t);
    *cos_t = ct;
    float rs = (cos_i - eta * ct) / (cos_i + eta * ct);
    float rp = (eta * cos_i - ct) / (eta * cos_i + ct);
    return 0.5f * (rs * rs + rp * rp);
}

// Fresnel reflectance of a conductor of complex index eta + i k at cos_i > 0, unpolarised
// (the exact expression for s and p waves, e.g. pbrt-v3 sec. 8.2.1).
inline float3 fresnel_conductor(float cos_i, float3 eta, float3 k) {
    float c2 = cos_i * cos_i, s2 = 1.0f - c2;
    float3 e2 = eta * eta, k2 = k * k;
    float3 t0 = e2 - k2 - (float3)(s2);
    float3 a2b2 = sqrt(t0 * t0 + 4.0f * e2 * k2);
    float3 a = sqrt(fmax(0.5f * (a2b2 + t0), 0.0f));
    float3 t1 = a2b2 + (float3)(c2), t2 = 2.0f * cos_i * a;
    float3 rs = (t1 - t2) / (t1 + t2);
    float3 t3 = c2 * a2b2 + (float3)(s2 * s2), t4 = t2 * s2;
    float3 rp = rs * (t3 - t4) / (t3 + t4);
    return 0.5f * (rs + rp);
}

// A conductor's reflectance at cos_i: its specular tint, times the Fresnel term unless
// MF_NO_FRESNEL (a perfect reflector).
inline float3 conductor_reflectance(const Material* m, float cos_i) {
    return (m->flags & MF_NO_FRESNEL) ? m->base : m->base * fresnel_conductor(cos_i, m->eta, m->second);
}

// Isotropic microfacet distributions of roughness alpha (Walter et al. 2007): the normal
// density D(h) at cos_h, Beckmann D = exp(-tan^2/a^2) / (pi a^2 cos^4), GGX
// D = a^2 / (pi cos^4 (a^2 + tan^2)^2); Smith's masking G1 of direction v (cos_v to the
// macro normal, cos_vh to h): GGX 2 / (1 + sqrt(1 + a^2 tan^2)), Beckmann by Walter's rational
// fit in b = 1 / (a tan) (1 for b >= 1.6); 0 where v sees the back of h.
inline float mf_d(float cos_h, float alpha, bool beckmann) {
    if (cos_h <= 0.0f) return 0.0f;
    float c2 = cos_h * cos_h, t2 = (1.0f - c2) / c2, a2 = alpha * alpha;
    if (beckmann) return exp(-t2 / a2) / (PI_F * a2 * c2 * c2);
    float r = a2 + t2;
    return a2 / (PI_F * c2 * c2 * r * r);
}

inline float mf_g1(float cos_v, float cos_vh, float alpha, bool beckmann) {
    if (cos_vh * cos_v <= 0.0f) return 0.0f;
    float c2 = cos_v * cos_v, t2 = fmax(1.0f - c2, 0.0f) / c2;
    if (t2 == 0.0f) return 1.0f;
    if (!beckmann) return 2.0f / (1.0f + sqrt(1.0f + alpha * alpha * t2));
    float b = 1.0f / (alpha * sqrt(t2));
    return b >= 1.6f ? 1.0f : (3.535f * b + 2.181f * b * b) / (1.0f + 2.276f * b + 2.577f * b * b);
}

// A microfacet normal about n with density D(h) cos_h (the pdf mf_d(cos_h) cos_h).
inline float3 mf_sample(float3 n, float alpha, bool beckmann, float u1, float u2) {
    float a2 = alpha * alpha;
    float t2 = beckmann ? -a2 * log(1.0f - u1) : a2 * u1 / (1.0f - u1);
    float c = 1.0f / sqrt(1.0f + t2), s = sqrt(fmax(0.0f, 1.0f - c * c)), phi = 2.0f * PI_F * u2;
    return from_local(n, s * cos(phi), s * sin(phi), c);
}

// rough_plastic's coat transmittance at cos (its table, linear between TABLE_SIZE cosines
// evenly spaced over [0, 1]).
inline float coat_transmittance(const Material* m, float cos_v) {
    float x = clamp(cos_v, 0.0f, 1.0f) * (float)(TABLE_SIZE - 1);
    int i = min((int)x, TABLE_SIZE - 2);
    return mix(m->table[i], m->table[i + 1], x - (float)i);
}

// Shading normals (smooth meshes) bend lobes, but sides stay geometric (Veach 1997, sec. 5.3).
// Photons arriving along d: the flux per geometric area, weighted |wi.ns| / |wi.ng|, is what
// a BSDF that uses ns sees; 0 for light from below ns.
inline float shading_arrival(float3 d, float3 ng, float3 ns) {
    float gi = dot(d, ng), si = dot(d, ns);
    return gi * si > 0.0f ? si / gi : 0.0f;
}

// A bounce d -> nd: 0 where a direction lies on different sides of ns and ng (no light leaks
// through the true surface); else the adjoint BSDF's |wi.ns| |wo.ng| / (|wi.ng| |wo.ns|) for
// photon paths and 1 for eye paths.
inline float shading_bounce(float3 d, float3 nd, float3 ng, float3 ns, bool photon) {
    float arrive = shading_arrival(d, ng, ns);
    float go = dot(nd, ng), so = dot(nd, ns);
    if (arrive == 0.0f || go * so <= 0.0f) return 0.0f;
    return photon ? arrive * go / so : 1.0f;
}

// Octahedral packing of a unit vector into 2 x 16 bits (photon incoming directions).
inline uint pack_dir(float3 v) {
    v /= fabs(v.x) + fabs(v.y) + fabs(v.z);
    float2 p = v.xy;
    if (v.z < 0.0f) {
        p = (float2)((1.0f - fabs(v.y)) * (v.x >= 0.0f ? 1.0f : -1.0f),
                     (1.0f - fabs(v.x)) * (v.y >= 0.0f ? 1.0f : -1.0f));
    }
    uint2 q = convert_uint2_sat_rte((p * 0.5f + 0.5f) * 65535.0f);
    return q.x | (q.y << 16);
}

inline float3 unpack_dir(uint bits) {
    float2 p = (float2)((float)(bits & 0xFFFFu), (float)(bits >> 16)) / 65535.0f * 2.0f - 1.0f;
    float3 v = (float3)(p.x, p.y, 1.0f - fabs(p.x) - fabs(p.y));
    if (v.z < 0.0f) {
        v.xy = (float2)((1.0f - fabs(p.y)) * (p.x >= 0.0f ? 1.0f : -1.0f),
                        (1.0f - fabs(p.x)) * (p.y >= 0.0f ? 1.0f : -1.0f));
    }
    return normalize(v);
}
