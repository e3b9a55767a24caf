// Rays, shapes and the BVH: closest-hit queries against spheres and triangles, and
// any-hit visibility queries (occluded).
//
// Spheres are intersected in double precision: smallppm's walls are spheres of radius
// 1e5, and the float32 quadratic loses every digit of the hit distance to cancellation.

#define SURF_NONE (-1)
#define HIT_EPS_REL 1e-5f

typedef struct {
    float t;
    float3 ng;    // geometric normal, oriented as the shape defines its front side
    float3 ns;    // shading normal, on ng's side: ng itself unless the mesh has normals
    bool smooth;  // ns is interpolated (ns == ng bit for bit otherwise)
    int surf;     // surface record index, SURF_NONE on a miss
    int tri;      // the triangle hit, or -1 (a sphere, or a miss)
    int sphere;   // the sphere hit, or -1 (a triangle, or a miss)
} Hit;

inline double sphere_distance(float4 sph, float3 o, float3 d, double tmin, double tmax) {
    double3 c = (double3)(sph.x, sph.y, sph.z);
    double3 f = convert_double3(o) - c;
    double3 dd = convert_double3(d);
    double b = dot(f, dd);
    double3 perp = f - b * dd;   // perpendicular offset: robust discriminant
    double r = (double)sph.w;
    double disc = r * r - dot(perp, perp);
    if (disc < 0.0) return tmax;
    double s = sqrt(disc);
    double q = (b > 0.0) ? -b - s : -b + s;
    double t0 = (dot(f, f) - r * r) / q, t1 = q;
    if (t0 > t1) { double tmp = t0; t0 = t1; t1 = tmp; }
    if (t0 > tmin && t0 < tmax) return t0;
    if (t1 > tmin && t1 < tmax) return t1;
    return tmax;
}

// The ray queries' inner loops spell out dot, cross, fmin, fmax and fabs: PoCL calls its builtins
// out of line, and these run for every triangle and box a ray meets. Each is the builtin's
// arithmetic in the builtin's order with no contraction into fma, so the bits are the same:
// dot ((x + y) + z), cross's three differences, and fmin / fmax returning a when b is NaN.
inline float dot3(float3 a, float3 b) {
#pragma OPENCL FP_CONTRACT OFF
    return (a.x * b.x + a.y * b.y) + a.z * b.z;
}

inline float3 cross3(float3 a, float3 b) {
#pragma OPENCL FP_CONTRACT OFF
    return (float3)(a.y * b.z - a.z * b.y, a.z * b.x - a.x * b.z, a.x * b.y - a.y * b.x);
}

inline float min1(float a, float b) { return b != b ? a : (a < b ? a : b); }  // b != b: b is NaN
inline float max1(float a, float b) { return b != b ? a : (a > b ? a : b); }

// Moller-Trumbore; returns t or `tmax` on a miss.
inline float triangle_distance(float3 v0, float3 e1, float3 e2, float3 o, float3 d, float tmin, float tmax) {
    float3 p = cross3(d, e2);
    float det = dot3(e1, p);
    if (det < 1e-20f && det > -1e-20f) return tmax;  // |det| < 1e-20 (fabs is a call too)
    float inv = 1.0f / det;
    float3 s = o - v0;
    float u = dot3(s, p) * inv;
    if (u < 0.0f || u > 1.0f) return tmax;
    float3 q = cross3(s, e1);
    float v = dot3(d, q) * inv;
    if (v < 0.0f || u + v > 1.0f) return tmax;
    float t = dot3(e2, q) * inv;
    return (t > tmin && t < tmax) ? t : tmax;
}

// Barycentrics (u, v) along e1, e2 of where the ray meets the triangle's plane.
inline float2 triangle_uv(float3 v0, float3 e1, float3 e2, float3 o, float3 d) {
    float3 p = cross(d, e2), s = o - v0, q = cross(s, e1);
    float inv = 1.0f / dot(e1, p);
    return (float2)(dot(s, p) * inv, dot(d, q) * inv);
}

inline bool box_hit(float4 lo, float4 hi, float3 o, float3 inv_d, float tmax) {
    float3 t0 = (lo.xyz - o) * inv_d, t1 = (hi.xyz - o) * inv_d;
    float enter = max1(max1(min1(t0.x, t1.x), min1(t0.y, t1.y)), max1(min1(t0.z, t1.z), 0.0f));
    float leave = min1(min1(max1(t0.x, t1.x), max1(t0.y, t1.y)), min1(max1(t0.z, t1.z), tmax));
    return enter <= leave;
}

typedef struct {
    __global const float4* tri_v0;   // w: surface index (int bits)
    __global const float4* tri_e1;   // w: 1 if the triangle has shading normals
    __global const float4* tri_e2;
    __global const float4* tri_nrm;  // 3 rows per triangle: corner normals (smooth triangles only)
    __global const int4* tri_adj;    // the triangle across each edge on the same surface, or -1; w: the
                                     // float bits of its far-edge bound (worker/adjacency.py; eye_pass.cl)
    __global const float4* node_lo;  // see worker/bvh.py for the layout
    __global const float4* node_hi;
    __global const float4* spheres;  // xyz centre, w radius
    __global const int* sphere_surf;
    int n_nodes;
    int n_spheres;
    float eps_floor;                 // the scene's coordinate scale, at most 1 (ray_eps)
    __global const float4* tex_info;    // texture records (textures.cl)
    __global const uchar* tex_texels;   // their texels (bytes)
    __global const float2* tex_uv;      // 3 rows per triangle: corner texture coordinates (textured scenes only)
} SceneGeom;

// Ray offset: 1e-5 of the magnitude of the coordinates it is added to (some 80 float32 ulps),
// and near the origin 1e-5 of the scene's own scale (eps_floor, worker/scene_arrays.py), so that
// the image does not change with the scene's unit or its distance from the origin. Every ray
// that leaves a surface starts this far off it along the normal, on the side it leaves to, so
// it cannot meet that surface again; the queries below then take every hit ahead of the origin
// (t > 0). No skip along the ray as well: a ray that left within it of a wall would cross the
// wall at a concave corner (tests/test_wall_leak.py).
inline float ray_eps(const SceneGeom* g, float3 p) {
    return HIT_EPS_REL * fmax(g->eps_floor, fmax(fabs(p.x), fmax(fabs(p.y), fabs(p.z))));
}

// Triangle `tri`'s corners v0, v0 + e1, v0 + e2 (edge j runs from corner j to corner j + 1:
// the order of tri_adj's neighbours, worker/adjacency.py).
inline void triangle_corners(const SceneGeom* g, int tri, float3 a[3]) {
    a[0] = g->tri_v0[tri].xyz;
    a[1] = a[0] + g->tri_e1[tri].xyz;
    a[2] = a[0] + g->tri_e2[tri].xyz;
}

// The scene's buffers as every tracing kernel takes them, in the host's order (Device.geometry,
// then Device.emitter_args, worker/engine.py), and the SceneGeom a kernel makes of them.
#define SCENE_PARAMS \
    __global const float4* tri_v0, __global const float4* tri_e1, __global const float4* tri_e2, \
    __global const float4* tri_nrm, __global const int4* tri_adj, \
    __global const float4* node_lo, __global const float4* node_hi, int n_nodes, \
    __global const float4* spheres, __global const int* sphere_surf, int n_spheres, float eps_floor, \
    __global const float4* surfaces, \
    __global const float4* tex_info, __global const uchar* tex_texels, __global const float2* tex_uv, \
    __global const float4* emitters, __global const float* emitter_cdf, int n_emitters
#define SCENE_GEOM {tri_v0, tri_e1, tri_e2, tri_nrm, tri_adj, node_lo, node_hi, spheres, sphere_surf, n_nodes, \
                    n_spheres, eps_floor, tex_info, tex_texels, tex_uv}

// No point of the sphere lies within tmax of o: a bounded query skips it (smallppm's walls
// are spheres of radius 1e5, so the distance is taken in double).
inline bool sphere_beyond(float4 sph, float3 o, float tmax) {
    double3 f = convert_double3(o) - (double3)(sph.x, sph.y, sph.z);
    return fabs(sqrt(dot(f, f)) - (double)sph.w) > (double)tmax;
}

// The closest hit within distance tmax (SURF_NONE if there is none that close).
inline Hit intersect_within(const SceneGeom* g, float3 o, float3 d, float tmax) {
    Hit h;
    h.t = tmax;
    h.surf = SURF_NONE;
    h.tri = -1;
    h.sphere = -1;
    float tmin = 0.0f;
    int best_sphere = -1, best_tri = -1;
    bool bounded = tmax < INFINITY;
    for (int i = 0; i < g->n_spheres; ++i) {
        if (bounded && sphere_beyond(g->spheres[i], o, tmax)) continue;
        double t = sphere_distance(g->spheres[i], o, d, (double)tmin, (double)h.t);
        if (t < (double)h.t) { h.t = (float)t; best_sphere = i; }
    }
    if (g->n_nodes > 0) {
        float3 inv_d = 1.0f / d;
        int stack[64];
        int sp = 0;
        int node = 0;
        while (true) {
            float4 lo = g->node_lo[node], hi = g->node_hi[node];
            if (box_hit(lo, hi, o, inv_d, h.t)) {
                int a = as_int(lo.w), count = as_int(hi.w);
                if (count > 0) {
                    for (int k = a; k < a + count; ++k) {
                        float t = triangle_distance(g->tri_v0[k].xyz, g->tri_e1[k].xyz, g->tri_e2[k].xyz, o, d, tmin, h.t);
                        if (t < h.t) { h.t = t; best_tri = k; best_sphere = -1; }
                    }
                } else {
                    stack[sp++] = a;      // right child later
                    node = node + 1;      // left child is next in pre-order
                    continue;
                }
            }
            if (sp == 0) break;
            node = stack[--sp];
        }
    }
    if (best_tri >= 0) {
        h.tri = best_tri;
        float4 e1 = g->tri_e1[best_tri];
        h.ng = normalize(cross(e1.xyz, g->tri_e2[best_tri].xyz));
        h.surf = as_int(g->tri_v0[best_tri].w);
        h.ns = h.ng;
        h.smooth = e1.w != 0.0f;
        if (h.smooth) {  // interpolate the corner normals, turned to ng's side
            float2 uv = triangle_uv(g->tri_v0[best_tri].xyz, e1.xyz, g->tri_e2[best_tri].xyz, o, d);
            __global const float4* n = g->tri_nrm + 3 * best_tri;
            float3 ns = (1.0f - uv.x - uv.y) * n[0].xyz + uv.x * n[1].xyz + uv.y * n[2].xyz;
            float len = length(ns);
            if (len > 1e-6f) h.ns = dot(ns, h.ng) < 0.0f ? -ns / len : ns / len;
        }
    } else if (best_sphere >= 0) {
        float4 s = g->spheres[best_sphere];
        h.ng = normalize(o + h.t * d - s.xyz);
        h.ns = h.ng;
        h.smooth = false;
        h.surf = g->sphere_surf[best_sphere];
        h.sphere = best_sphere;
    }
    return h;
}

inline Hit intersect(const SceneGeom* g, float3 o, float3 d) { return intersect_within(g, o, d, INFINITY); }

// Whether anything lies within distance tmax along the ray: a visibility (shadow) ray. The
// same traversal as intersect_within, but it stops at the first hit and makes no hit record:
// until its first hit the closest-hit query visits the same nodes with the same bound, so
// the answer is intersect_within(...).surf != SURF_NONE bit for bit.
inline bool occluded(const SceneGeom* g, float3 o, float3 d, float tmax) {
    float tmin = 0.0f;
    bool bounded = tmax < INFINITY;
    for (int i = 0; i < g->n_spheres; ++i) {
        if (bounded && sphere_beyond(g->spheres[i], o, tmax)) continue;
        if (sphere_distance(g->spheres[i], o, d, (double)tmin, (double)tmax) < (double)tmax) return true;
    }
    if (g->n_nodes == 0) return false;
    float3 inv_d = 1.0f / d;
    int stack[64];
    int sp = 0;
    int node = 0;
    while (true) {
        float4 lo = g->node_lo[node], hi = g->node_hi[node];
        if (box_hit(lo, hi, o, inv_d, tmax)) {
            int a = as_int(lo.w), count = as_int(hi.w);
            if (count == 0) {
                stack[sp++] = a;      // right child later
                node = node + 1;      // left child is next in pre-order
                continue;
            }
            for (int k = a; k < a + count; ++k)
                if (triangle_distance(g->tri_v0[k].xyz, g->tri_e1[k].xyz, g->tri_e2[k].xyz, o, d, tmin, tmax) < tmax)
                    return true;
        }
        if (sp == 0) return false;
        node = stack[--sp];
    }
}

// Whether anything lies between two points, each already off its surface on the side facing
// the other (a shadow ray or a connection, aimed at the far point's own offset point and ending
// there). A ray aimed at the far surface point and stopped short of it along the ray instead
// ends beyond a wall that stands within that distance of the point, at a concave corner, and
// sees the point through the wall.
inline bool blocked_between(const SceneGeom* g, float3 o, float3 e) {
    float3 d = e - o;
    float len = length(d);
    return len > 0.0f && occluded(g, o, d / len, len);
}
