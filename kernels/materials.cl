// Materials: one surface record per shape, and how a path leaves a surface.
//
// surf_a = (albedo rgb, type as int bits), surf_b = (emission rgb, parameter), where the
// parameter is the IOR for glass and the Phong exponent for glossy. Diffuse surfaces end
// eye paths (measurement points) and store photons; mirror, glass and glossy surfaces are
// scattered through by both eye and photon paths (digest 5.2: SPPM follows glossy lobes
// with a sampled bounce, so glossy cost does not depend on the exponent).
// The type codes MAT_* come from kernels/contract.py as build options.

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

// Unpolarised Fresnel reflectance of a dielectric interface.
inline float fresnel_dielectric(float cos_i, float cos_t, float eta) {
    // eta = n_incident / n_transmitted
    float rs = (eta * cos_i - cos_t) / (eta * cos_i + cos_t);
    float rp = (cos_i - eta * cos_t) / (cos_i + eta * cos_t);
    return 0.5f * (rs * rs + rp * rp);
}

// Continue a path through a mirror, glass or glossy surface hit along `d`.
// Writes the new direction and the throughput factor f*cos/pdf; false if the path ends.
// Refraction carries no (eta_i/eta_t)^2 radiance factor: eye paths start and end in air
// in every scene here, where the factors of entering and leaving cancel. Lobes turn about
// the shading normal ns; the geometric ng says which side the path comes from.
inline bool scatter_specular(int type, float param, float3 albedo, float3 d, float3 ng, float3 ns, Rng* rng,
                             float3* new_d, float3* weight) {
    float3 n = dot(d, ng) < 0.0f ? ns : -ns;  // faces the incoming path
    if (type == MAT_MIRROR) {
        *new_d = reflect_dir(d, n);
        *weight = albedo;
        return true;
    }
    if (type == MAT_GLASS) {
        bool entering = dot(d, ng) < 0.0f;
        float eta = entering ? 1.0f / param : param;
        float cos_i = -dot(d, n);
        float sin2_t = eta * eta * fmax(0.0f, 1.0f - cos_i * cos_i);
        *weight = albedo;
        if (sin2_t >= 1.0f) {  // total internal reflection
            *new_d = reflect_dir(d, n);
            return true;
        }
        float cos_t = sqrt(1.0f - sin2_t);
        // Russian roulette between the two branches with the Fresnel probability:
        // the branch weight F/F = (1-F)/(1-F) = 1.
        if (rng_float(rng) < fresnel_dielectric(cos_i, cos_t, eta)) {
            *new_d = reflect_dir(d, n);
        } else {
            *new_d = normalize(eta * d + (eta * cos_i - cos_t) * n);
        }
        return true;
    }
    // Modified Phong: f = rho (e+2)/(2 pi) cos^e(a), lobe pdf (e+1)/(2 pi) cos^e(a),
    // so f cos(theta)/pdf = rho (e+2)/(e+1) cos(theta).
    float e = param;
    float cos_a = pow(rng_float(rng), 1.0f / (e + 1.0f));
    float sin_a = sqrt(fmax(0.0f, 1.0f - cos_a * cos_a));
    float phi = 2.0f * PI_F * rng_float(rng);
    float3 w = from_local(reflect_dir(d, n), sin_a * cos(phi), sin_a * sin(phi), cos_a);
    float cos_theta = dot(w, n);
    if (cos_theta <= 0.0f) return false;  // sampled below the surface: absorbed
    *new_d = w;
    *weight = albedo * ((e + 2.0f) / (e + 1.0f) * cos_theta);
    return true;
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
