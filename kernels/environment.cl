// The environment light (`environment`): radiance L(w) arriving from infinitely far along
// every direction, w pointing from the scene toward the sky. At most one per scene; its
// record is the last of the emitter table (lights.cl; worker/env_light.py):
//   row0 = (centre c of the scene's bounding sphere, kind), row1 = (constant radiance, R),
//   row2 = (x: int bits of the first row of its map in the table, 0 for a constant),
//   row3 = (power pi R^2 int L dw, selection probability).
// A map's rows in the table: three rows of the world-to-local rotation (w: the map's width W
// and height H as int bits, then 0), the W x H radiance samples (scale applied), then the
// distribution's float32 CDFs packed four a row: the marginal over the H - 1 cell rows, then
// per cell row the conditional over its W cells.
//
// A map is read as Mitsuba 3's envmap reads it: in the local frame, w = (sin t sin p, cos t,
// -sin t cos p) for t in [0, pi] from +y and p = atan2(w.x, -w.z); sample (row j, column i)
// sits at grid point (x, y) = (i, j), x = p W / (2 pi) - 1/2 (wrapping), y = t (H - 1) / pi,
// and L is bilinear between grid points (the last column's right neighbour is the first).
//
// Sampling (pbrt-v4 sec. 12.5.2, "Image Infinite Lights"; Pharr et al. 2023): the grid's
// cells, W x (H - 1), are chosen with probability P_ij proportional to the cell's mean
// sample times its solid angle (the mean of the corners is the integral of the bilinear L
// over the cell, and zero only where L is zero throughout it), a point uniformly inside,
// and the density in solid angle of a direction in cell ij is
//     pdf(w) = P_ij W (H - 1) / (2 pi^2 sin t)
// (dw = sin t dt dp, dt dp = 2 pi^2 / (W (H - 1)) dx dy). A constant is sampled uniformly,
// pdf = 1 / (4 pi). Emission (photons, light subpaths) as for the directional light: a
// direction -w with w from the same distribution, from a point of the disc of radius R
// facing w at distance R from c, so that every ray of that direction through the scene's
// bounding sphere is drawn: position pdf 1 / (pi R^2), flux L(w) pi R^2 / pdf(w).

// Index of the first entry of the n-entry CDF that exceeds u (the last if none does).
inline int cdf_search(__global const float* cdf, int n, float u) {
    int lo = 0, hi = n - 1;
    while (lo < hi) {
        int mid = (lo + hi) / 2;
        if (cdf[mid] > u) hi = mid; else lo = mid + 1;
    }
    return lo;
}

// The environment's record index, or -1 if the scene has none.
inline int env_record(__global const float4* emitters, int n_emitters) {
    return n_emitters > 0 && as_int(emitters[4 * (n_emitters - 1)].w) == EMIT_ENVIRONMENT ? n_emitters - 1 : -1;
}

typedef struct {
    __global const float4* rot;    // world-to-local rows (0 for a constant)
    __global const float4* texels; // W x H, row-major
    __global const float* marginal, *conditional;
    int width, height;             // 0 for a constant
    float3 uniform;  // a constant's radiance
} EnvMap;

inline EnvMap env_map(__global const float4* emitters, int k) {
    EnvMap e;
    e.uniform = emitters[4 * k + 1].xyz;
    int row = as_int(emitters[4 * k + 2].x);
    e.width = e.height = 0;
    if (row == 0) return e;
    e.rot = emitters + row;
    e.width = as_int(e.rot[0].w);
    e.height = as_int(e.rot[1].w);
    e.texels = e.rot + 3;
    e.marginal = (__global const float*)(e.texels + e.width * e.height);
    e.conditional = e.marginal + (e.height - 1);
    return e;
}

// The grid point (x, y) of direction w (world), and sin t.
inline float2 env_grid(const EnvMap* e, float3 w, float* sin_t) {
    float3 l = (float3)(dot(e->rot[0].xyz, w), dot(e->rot[1].xyz, w), dot(e->rot[2].xyz, w));
    *sin_t = sqrt(l.x * l.x + l.z * l.z);
    float x = atan2(l.x, -l.z) * (0.5f / PI_F) * (float)e->width - 0.5f;
    x -= (float)e->width * floor(x / (float)e->width);
    float y = acos(clamp(l.y, -1.0f, 1.0f)) / PI_F * (float)(e->height - 1);
    return (float2)(x, y);
}

// The cell (i, j) of grid point g, and its probability P_ij.
inline float env_cell(const EnvMap* e, float2 g, int* i, int* j) {
    *i = min((int)g.x, e->width - 1);
    *j = min((int)g.y, e->height - 2);
    __global const float* row = e->conditional + *j * e->width;
    float pm = e->marginal[*j] - (*j > 0 ? e->marginal[*j - 1] : 0.0f);
    float pc = row[*i] - (*i > 0 ? row[*i - 1] : 0.0f);
    return pm * pc;
}

// P_ij as a density in solid angle at sin t (the header's pdf(w)); sin t at least 1e-7, so
// that a sample at a pole keeps a finite density (and a negligible weight L / pdf).
inline float env_density(const EnvMap* e, float p_cell, float sin_t) {
    return p_cell * (float)(e->width * (e->height - 1)) / (2.0f * PI_F * PI_F * fmax(sin_t, 1e-7f));
}

// L(w), w (world) toward the sky.
inline float3 env_radiance(__global const float4* emitters, int k, float3 w) {
    EnvMap e = env_map(emitters, k);
    if (e.width == 0) return e.uniform;
    float sin_t;
    float2 g = env_grid(&e, w, &sin_t);
    int i, j;
    env_cell(&e, g, &i, &j);
    float fx = g.x - (float)i, fy = g.y - (float)j;
    int i1 = i + 1 == e.width ? 0 : i + 1;
    __global const float4* r0 = e.texels + j * e.width;
    __global const float4* r1 = r0 + e.width;
    float3 top = (1.0f - fx) * r0[i].xyz + fx * r0[i1].xyz, bottom = (1.0f - fx) * r1[i].xyz + fx * r1[i1].xyz;
    return (1.0f - fy) * top + fy * bottom;
}

// The density in solid angle (no selection probability) of env_sample choosing w.
inline float env_pdf(__global const float4* emitters, int k, float3 w) {
    EnvMap e = env_map(emitters, k);
    if (e.width == 0) return 1.0f / (4.0f * PI_F);
    float sin_t;
    float2 g = env_grid(&e, w, &sin_t);
    int i, j;
    return env_density(&e, env_cell(&e, g, &i, &j), sin_t);
}

// A direction w (world, toward the sky) from two uniform numbers, and its density `pdf`.
inline float3 env_sample(__global const float4* emitters, int k, float u1, float u2, float* pdf) {
    EnvMap e = env_map(emitters, k);
    if (e.width == 0) {
        *pdf = 1.0f / (4.0f * PI_F);
        return sample_sphere(u1, u2);
    }
    int j = cdf_search(e.marginal, e.height - 1, u1);
    __global const float* row = e.conditional + j * e.width;
    int i = cdf_search(row, e.width, u2);
    float m0 = j > 0 ? e.marginal[j - 1] : 0.0f, c0 = i > 0 ? row[i - 1] : 0.0f;
    float pm = e.marginal[j] - m0, pc = row[i] - c0;
    // Where the number fell within the chosen interval: the point's place in the cell.
    float y = (float)j + (pm > 0.0f ? clamp((u1 - m0) / pm, 0.0f, 1.0f) : 0.5f);
    float x = (float)i + (pc > 0.0f ? clamp((u2 - c0) / pc, 0.0f, 1.0f) : 0.5f);
    float t = y * PI_F / (float)(e.height - 1), p = (x + 0.5f) * 2.0f * PI_F / (float)e.width;
    float sin_t = sin(t);
    float3 l = (float3)(sin_t * sin(p), cos(t), -sin_t * cos(p));
    *pdf = env_density(&e, pm * pc, sin_t);
    return normalize(l.x * e.rot[0].xyz + l.y * e.rot[1].xyz + l.z * e.rot[2].xyz);
}

// The environment's radiance along a ray that leaves the scene in direction d, and in
// `p_light` the density in solid angle, with the selection probability, of the light sample
// (lights.cl, sample_direct) choosing d: what a BSDF-sampled direction's MIS weight needs.
// 0 without an environment.
inline float3 env_escape(__global const float4* emitters, int n_emitters, float3 d, float* p_light) {
    int k = env_record(emitters, n_emitters);
    *p_light = 0.0f;
    if (k < 0) return (float3)(0.0f);
    *p_light = emitters[4 * k + 3].w * env_pdf(emitters, k, d);
    return env_radiance(emitters, k, d);
}

// The position pdf 1 / (pi R^2) of the environment's emission (its disc; 0 without one).
inline float env_position_pdf(__global const float4* emitters, int n_emitters) {
    int k = env_record(emitters, n_emitters);
    float r = k < 0 ? 0.0f : emitters[4 * k + 1].w;
    return k < 0 ? 0.0f : 1.0f / (PI_F * r * r);
}

// A ray from the environment into the scene (header): origin o, direction d = -w, the
// direction's density pdf_w (no selection probability), and flux L(w) pi R^2 / pdf_w (no
// selection probability either).
typedef struct { float3 o, d, flux; float pdf_w; } EnvRay;

inline EnvRay env_emit(__global const float4* emitters, int k, float u1, float u2, float u3, float u4) {
    float4 r0 = emitters[4 * k], r1 = emitters[4 * k + 1];
    EnvRay r;
    float3 w = env_sample(emitters, k, u1, u2, &r.pdf_w);
    float3 t, b;
    onb(w, &t, &b);
    float rr = r1.w * sqrt(u3), phi = 2.0f * PI_F * u4;
    r.o = r0.xyz + r1.w * w + rr * (cos(phi) * t + sin(phi) * b);
    r.d = -w;
    r.flux = env_radiance(emitters, k, w) * (PI_F * r1.w * r1.w / r.pdf_w);
    return r;
}
