// Eye pass: one measurement point per pixel and pass (SPPM, dissertation ch. 7).
//
// A jittered sub-pixel sample (and lens sample) is followed through the surfaces it meets;
// at each the path takes one part of the BSDF (bsdf.cl): the diffuse part makes this pass's
// measurement point, with weight = path throughput * g(wo) / pi (over the part's
// probability) and the share of its gather disc that lies on its own surface
// (disc_coverage); any other part is sampled on. Emission seen along the way is accumulated
// separately into the batch's per-pixel sums (SUM_LD; digest 5.1: directly visible
// emission is averaged over passes). In PPM mode the host always passes pass index 0, so
// every pass sees the same points. Direct light is estimated by light samples (lights.cl)
// and added to SUM_LD, from its own random stream keyed by the real pass index (so PPM's
// fixed points still get a new light sample every pass): at every glossy vertex before the
// point (photons are stored on diffuse parts only), MIS-weighted against the path's own
// next bounce (as pbrt-v4's SPPM), so that a glossy surface sees point and spot lights,
// which no bounce can hit; and with `nee` at the point, through the diffuse part. SUM_LD2,
// where the layout has it, adds the square of the pass's Ld luminance for the error estimate.

// Surfaces match when their normals lie within 45 degrees (NORMAL_MATCH_COS, contract.py). A
// smooth surface of curvature radius rho turns its normal by r / rho across a disc of radius
// r, so it keeps every photon while r < 0.78 rho.
#define COVERAGE_RAYS 8  // 8: two words of 8-bit cuts (inside_cut)
#define CUT_NONE 0xFFFFFFFFu  // every ray's cut at 255: the whole disc
// The coverage rays reach 1 / cos(pi / COVERAGE_RAYS) of the radius: a straight wall that cuts
// the disc then meets at least one ray (the one nearest its closest point), also where it cuts
// only the rim between two rays, whose photons the gather would otherwise take.
#define CUT_REACH 1.0824f
#define CUT_INNER 0.7071f  // sin(2 pi / COVERAGE_RAYS), rounded down (inside_cut)
#define OWN_SURFACE_COS 0.9999  /* the point's normal is the sphere's (inward) normal */

// A ray's cut in units of r from its 8-bit code: 255, no cut within the reach (a ray that found
// none is taken to end at the reach: between it and a cut ray the wall lies beyond that edge).
inline float cut_at_q(uint q) { return q == 255u ? CUT_REACH : (float)q / 255.0f * CUT_REACH; }

// Ray k's cut, in units of r (cut_at_q), from the cut's words.
inline float cut_at(uint4 cut, int k) {
    uint word = (k & 4) ? cut.y : cut.x;
    return cut_at_q((word >> (8 * (k & 3))) & 0xFFu);
}

// Share of the kernel weight of the tangent disc (radius r about x, normal n) that lies on
// the point's own surface: where a concave corner's wall cuts the disc, or the surface ends
// in empty space (a convex edge: a table top's rim), no photon of this surface lies beyond,
// and without the correction the estimate there is dark by that share (half the weight at
// the line). COVERAGE_RAYS rays along the surface, equally spaced and turned by a random
// angle, each find their cut: where a ray meets a non-matching surface, or where the
// point's surface ends (surface_extent), whichever is nearer. The cuts (8 bits a ray) and
// the rays' turn go to `cut`; the gather counts the photons on the centre's side of the
// chords that join neighbouring cuts (inside_cut), and the coverage is the kernel weight
// of exactly that part (sector_cover: 4 Gauss points a sector, along each the weight
// within the chord's distance, G(s) = int_0^s K(t) t dt / int_0^1 K(t) t dt
// = 3.5 s^2 - 14 s^5 + 17.5 s^6 - 6 s^7). Per chord rather than per ray (G of each ray's
// own cut), so the coverage leaves out the slivers between a chord and the disc's rim as
// the gather does; a coverage by ray counts them and darkens a straight edge. Returns the
// coverage of the disc of radius r and (same cuts) of radius r/2, for the error estimate's
// second gather radius (spatial_hash.cl). `smooth` false: the share of the disc's area
// instead, G(s) = s^2, for a uniform kernel (vcm's merging, vcm_camera_pass.cl).
inline float cover_share(float s) {
    float s2 = s * s;
    return s2 * (3.5f + s2 * s * (-14.0f + s * (17.5f - 6.0f * s)));
}

// Gauss-Legendre nodes of a sector's angle (4 points on [0, 1]: their angles' cos and sin
// for a sector of 2 pi / COVERAGE_RAYS, and their weights, summing to 1).
__constant float SECTOR_COS[4] = {0.99851352f, 0.96659819f, 0.86471718f, 0.74459627f};
__constant float SECTOR_SIN[4] = {0.05450462f, 0.25629657f, 0.50225910f, 0.66751509f};
__constant float SECTOR_WEIGHT[4] = {0.17392742f, 0.32607258f, 0.32607258f, 0.17392742f};

// The share of the kernel weight (G: cover_share, or s^2 for a uniform kernel) of one
// sector of the disc, between rays cut at s0 and s1 (units of r), that lies in the part
// inside_cut counts: on the centre's side of the chord joining the cut points, within the
// disc; and the same within r/2. In the sector's frame the first ray is the x axis; along
// a direction e the chord is met at rho = cross(d, -p0) / -cross(d, e), d = p1 - p0.
inline float2 sector_cover(float s0, float s1, bool smooth) {
    if (s0 == CUT_REACH && s1 == CUT_REACH) return (float2)(1.0f);  // no chord: the whole sector
    if (s0 == 0.0f && s1 == 0.0f) return (float2)(0.0f);             // beyond a wall at the point
    float2 p0 = (float2)(s0, 0.0f), p1 = s1 * (float2)(0.70710678f, 0.70710678f);
    float2 d = p1 - p0;
    float towards = d.y * p0.x - d.x * p0.y;  // cross(d, -p0) >= 0: the centre is inside
    float2 covered = (float2)(0.0f);
    for (int j = 0; j < 4; ++j) {
        float approach = d.y * SECTOR_COS[j] - d.x * SECTOR_SIN[j];  // -cross(d, e)
        float rho = approach > 0.0f ? fmax(towards, 0.0f) / approach : INFINITY;
        float s = fmin(rho, 1.0f), s_half = fmin(2.0f * rho, 1.0f);
        covered += SECTOR_WEIGHT[j] * (smooth ? (float2)(cover_share(s), cover_share(s_half))
                                              : (float2)(s * s, s_half * s_half));
    }
    return covered;
}

// Whether the coverage rays could meet anything that cuts the disc: a cheap conservative
// test, so that the rays are cast only near walls (most points find coverage 1). The rays
// run in the plane at height e = ray_eps(x) above the point, and reach CUT_REACH r. A shape
// cannot stop one if it lies farther than that from their origin, or wholly on one side of
// that plane (the point's own wall when it is convex or flat, every triangle of a flat
// floor), or if it is the concave sphere the point lies on (normal along its radius) with
// a radius of at least 2r: a chord shorter than CUT_REACH r turns its normal by under 32
// degrees, so any hit matches. When this says no, every ray would find no cut and the
// coverage is exactly (1, 1), so the image is the same bit for bit as with every disc traced.
inline bool plane_splits(float lowest, float highest, float e) { return lowest < 2.0f * e && highest > 0.5f * e; }

// Whether triangle (v0, v0 + e1, v0 + e2) may come within `reach` of x: its bounding box
// and its plane both do (conservative). A leaf holds several triangles (worker/bvh.py
// LEAF_SIZE), and its box reaching x says nothing of each, so each is tested: a leaf that
// holds a far wall beside the point's own would otherwise send every point's rays.
inline bool triangle_may_reach(float3 v0, float3 e1, float3 e2, float3 x, float reach) {
    float3 v1 = v0 + e1, v2 = v0 + e2;
    float3 nearest = clamp(x, fmin(v0, fmin(v1, v2)), fmax(v0, fmax(v1, v2)));
    if (dot(nearest - x, nearest - x) > reach * reach) return false;
    float3 c = cross(e1, e2);
    float d = dot(x - v0, c);
    return d * d <= reach * reach * dot(c, c);
}

inline bool disc_may_be_cut(const SceneGeom* g, float3 x, float3 n, float r) {
    float e = ray_eps(g, x);
    float reach = CUT_REACH * r + e;
    for (int i = 0; i < g->n_spheres; ++i) {
        float4 s = g->spheres[i];
        double3 f = convert_double3(x) - (double3)(s.x, s.y, s.z);
        double gap = sqrt(dot(f, f)) - (double)s.w;  // signed distance of x from the sphere's surface
        if (fabs(gap) > (double)reach) continue;
        double centre = -dot(f, convert_double3(n));  // height of the centre above the point's plane
        if (!plane_splits((float)(centre - (double)s.w), (float)(centre + (double)s.w), e)) continue;
        bool own_concave = fabs(gap) <= (double)e && centre >= OWN_SURFACE_COS * (gap + (double)s.w);
        if (own_concave && s.w >= 2.0f * r) continue;
        return true;
    }
    if (g->n_nodes == 0) return false;
    int stack[64];
    int sp = 0, node = 0;
    while (true) {
        float4 lo = g->node_lo[node], hi = g->node_hi[node];
        float3 nearest = clamp(x, lo.xyz, hi.xyz);
        if (dot(nearest - x, nearest - x) <= reach * reach) {
            int a = as_int(lo.w), count = as_int(hi.w);
            if (count == 0) {
                stack[sp++] = a;  // right child later
                node = node + 1;  // left child is next in pre-order
                continue;
            }
            for (int k = a; k < a + count; ++k) {
                float3 v0 = g->tri_v0[k].xyz, e1 = g->tri_e1[k].xyz, e2 = g->tri_e2[k].xyz;
                if (!triangle_may_reach(v0, e1, e2, x, reach + e)) continue;  // (e: slack for rounding)
                float h0 = dot(v0 - x, n), h1 = h0 + dot(e1, n), h2 = h0 + dot(e2, n);
                if (plane_splits(fmin(h0, fmin(h1, h2)), fmax(h0, fmax(h1, h2)), e)) return true;
            }
        }
        if (sp == 0) return false;
        node = stack[--sp];
    }
}

// How far the point's own surface runs from x along u (a unit vector in its tangent plane),
// up to `reach`: a walk from triangle `tri` across the edges the direction leaves through,
// to the neighbour on the same surface (worker/adjacency.py), until an edge with none (a
// convex edge, or a fold past NORMAL_MATCH_COS) or `reach`. u is turned into each
// triangle's plane; the distance is summed along the walk. Past EXTENT_STEPS triangles the
// surface is taken to run on (a mesh finer still), as it is on a sphere (tri < 0: closed).
inline float surface_extent(const SceneGeom* g, int tri, float3 x, float3 u, float reach) {
    float3 p = x;
    float travelled = 0.0f;
    int from = -1;
    for (int step = 0; step < EXTENT_STEPS && tri >= 0; ++step) {
        float3 a[3];
        triangle_corners(g, tri, a);
        float3 nt = normalize(cross(a[1] - a[0], a[2] - a[0]));
        float3 w = u - dot(u, nt) * nt;
        float lw = length(w);
        if (lw < 1e-6f) return travelled;  // the surface turns square to the direction: it ends
        w /= lw;
        // The edge the walk leaves through: the nearest whose outward normal (edge x nt) w goes along.
        int4 adj = g->tri_adj[tri];
        int across[3] = {adj.x, adj.y, adj.z};
        float leave = INFINITY;
        int edge = -1;
        for (int j = 0; j < 3; ++j) {
            if (across[j] == from && from >= 0) continue;  // the edge it came in by
            float3 out = cross(a[(j + 1) % 3] - a[j], nt);
            float along = dot(w, out);
            if (along <= 0.0f) continue;
            float s = dot(a[j] - p, out) / along;
            if (s < leave) { leave = s; edge = j; }
        }
        if (edge < 0) return travelled;
        travelled += fmax(leave, 0.0f);
        if (travelled >= reach) return reach;
        from = tri;
        tri = across[edge];
        if (tri < 0) return travelled;  // the surface ends at this edge
        p += fmax(leave, 0.0f) * w;
    }
    return reach;
}

// Whether x lies within `reach` of an edge of triangle `tri` where its surface ends (the
// distance to the edge's line: never more than to the edge).
inline bool near_open_edge(const SceneGeom* g, int tri, float3 x, float reach) {
    int4 adj = g->tri_adj[tri];
    int across[3] = {adj.x, adj.y, adj.z};
    float3 a[3];
    triangle_corners(g, tri, a);
    for (int j = 0; j < 3; ++j) {
        if (across[j] >= 0) continue;
        float3 d = a[(j + 1) % 3] - a[j], c = cross(x - a[j], d);
        if (dot(c, c) < reach * reach * dot(d, d)) return true;
    }
    return false;
}

// Whether the disc of radius `reach` about x, on triangle `tri`, may reach an edge where its
// surface ends. tri_adj.w is a bound per triangle (worker/adjacency.py, far_edge_bounds): its
// size how near the triangle comes to such an edge beyond its neighbours (a fine mesh), its
// sign whether the triangle or a neighbour has one, which is then tested from x itself.
inline bool disc_leaves_surface(const SceneGeom* g, int tri, float3 x, float reach) {
    if (tri < 0) return false;
    int4 adj = g->tri_adj[tri];
    float bound = as_float(adj.w);
    if (signbit(bound)) {
        int around[4] = {tri, adj.x, adj.y, adj.z};
        for (int j = 0; j < 4; ++j)
            if (around[j] >= 0 && near_open_edge(g, around[j], x, reach)) return true;
    }
    return fabs(bound) < reach;
}

inline float2 disc_coverage(const SceneGeom* g, float3 x, float3 n, int tri, float r, bool smooth, Rng* rng,
                            uint4* cut) {
    *cut = (uint4)(CUT_NONE, CUT_NONE, 0u, 0u);
    if (r <= 0.0f) return (float2)(1.0f);
    // Drawn whether or not the rays are cast, so the pretest leaves the path's later random
    // numbers (vcm's camera path goes on) as they were.
    float phi0 = rng_float(rng) * (2.0f * PI_F / COVERAGE_RAYS);
    float reach = CUT_REACH * r;
    bool edged = disc_leaves_surface(g, tri, x, reach);  // exact: the same with or without the pretest
    bool walled = true;
#if COVERAGE_PRETEST
    walled = disc_may_be_cut(g, x, n, r);
    if (!walled && !edged) return (float2)(1.0f);
#endif
    float3 t, b;
    onb(n, &t, &b);
    float3 o = x + n * ray_eps(g, x);
    uint words[2] = {0u, 0u};
    uint q_min = 255u;  // the nearest cut
    for (int k = 0; k < COVERAGE_RAYS; ++k) {
        float phi = phi0 + k * (2.0f * PI_F / COVERAGE_RAYS);
        float3 u = cos(phi) * t + sin(phi) * b;
        // The cut: a wall the ray meets, or the end of the point's surface, whichever is nearer.
        float end = edged ? surface_extent(g, tri, x, u, reach) : reach;
        if (walled) {
            Hit h = intersect_within(g, o, u, end);  // only what cuts the disc matters: the BVH prunes the rest
            if (h.surf != SURF_NONE && h.t < end) {
                float3 nh = dot(u, h.ng) < 0.0f ? h.ng : -h.ng;
                if (dot(nh, n) <= NORMAL_MATCH_COS) end = h.t;
            }
        }
        uint q = end < reach ? (uint)(end / reach * 255.0f) : 255u;
        words[k >> 2] |= q << (8 * (k & 3));
        q_min = min(q_min, q);
    }
    // w: the radius, in units of r, of a circle every edge of inside_cut lies beyond (an edge
    // between cuts at s_min r and farther, 2 pi / COVERAGE_RAYS apart, comes no nearer than
    // s_min r sin(2 pi / COVERAGE_RAYS)): a photon within it is inside with no angle to take.
    *cut = (uint4)(words[0], words[1], as_uint(phi0), as_uint(cut_at_q(q_min) * CUT_INNER));
    if (q_min == 255u) return (float2)(1.0f);
    // The kernel weight of the part the gather counts (inside_cut), sector by sector.
    float2 covered = (float2)(0.0f);
    for (int k = 0; k < COVERAGE_RAYS; ++k)
        covered += sector_cover(cut_at(*cut, k), cut_at(*cut, (k + 1) & (COVERAGE_RAYS - 1)), smooth);
    return covered / COVERAGE_RAYS;
}

// Whether a photon at offset v from the point lies in the covered part of its disc. The
// coverage rays' cut points, joined between neighbouring rays, bound that part (exact for
// a straight wall through the disc; between two uncut rays, the disc's rim). The coverage
// divides by the kernel weight of that part, so a photon beyond it (e.g. on the same plane
// behind a wall through the disc: a floor running under a partition into a lit room) must
// not count: it would be light leaking through the wall, amplified by the smaller coverage.
inline bool inside_cut(uint4 cut, float3 n, float3 v, float r) {
    if ((cut.x & cut.y) == CUT_NONE) return true;
    float inner = as_float(cut.w) * r;  // within it, inside (disc_coverage): most photons near a wall
    if (dot(v, v) < inner * inner) return true;
    float3 t, b;
    onb(n, &t, &b);
    float2 p = (float2)(dot(v, t), dot(v, b));
    float step = 2.0f * PI_F / COVERAGE_RAYS, phi0 = as_float(cut.z);
    int k = (int)floor((atan2(p.y, p.x) - phi0) / step) & (COVERAGE_RAYS - 1);  // between rays k and k + 1
    int k1 = (k + 1) & (COVERAGE_RAYS - 1);
    float s0 = cut_at(cut, k), s1 = cut_at(cut, k1);
    if (s0 == CUT_REACH && s1 == CUT_REACH) return true;  // the rim (the disc test is the caller's)
    // Both cut at the centre (a wall within the cut's quantum of the point, where it meets the
    // point's surface): the sector lies beyond it. The edge below would have no length and take
    // every photon in the sector.
    if (s0 == 0.0f && s1 == 0.0f) return false;
    float a0 = phi0 + k * step, a1 = a0 + step;
    float2 p0 = s0 * r * (float2)(cos(a0), sin(a0)), p1 = s1 * r * (float2)(cos(a1), sin(a1));
    float2 e = p1 - p0, w = p - p0;
    return e.x * w.y - e.y * w.x >= 0.0f;  // on the centre's side (left of p0 -> p1, counterclockwise)
}

typedef struct {
    float4 position;   // w: near clip distance along the view axis
    float4 forward;    // unit view axis; w: lens radius
    float4 right;      // scaled by tan(fov_x / 2); w: focus distance
    float4 up;         // scaled by tan(fov / 2)
} CameraDesc;

__kernel void eye_pass(
    SCENE_PARAMS,
    __global const CameraDesc* cam, int width, int height,
    int stride,                    // the point at gid is pixel gid * stride's (a set-up probe: > 1)
    ulong seed, uint pass, int max_bounces,
    int nee,                       // 1: estimate direct light at the point (lights.cl)
    uint light_pass,               // the real pass index: seeds the light samples
    __global const float* radius,  // the radius this pass gathers at (0: no coverage)
    __global float4* mp_pos,       // xyz; w: 1 if the pixel has a measurement point
    __global float4* mp_nrm,       // normal facing the eye path; w: disc coverage at r/2
    __global float4* mp_wgt,       // throughput * albedo / pi; w: disc coverage
    __global float* mp_dist,       // eye path length to the point (initial radius)
    __global uint4* mp_cut,        // the coverage rays' cuts (disc_coverage, inside_cut)
    __global double* batch_sums)   // per-pixel sums (sums.cl); += directly seen emission
{
    int gid = get_global_id(0), pixel = gid * stride;
    if (pixel >= width * height) return;
    SceneGeom g = SCENE_GEOM;
    Rng rng = rng_make(seed, pass, (uint)pixel, DOMAIN_EYE);

    int x = pixel % width, y = pixel / width;
    float sx = 2.0f * ((float)x + rng_float(&rng)) / (float)width - 1.0f;
    float sy = 1.0f - 2.0f * ((float)y + rng_float(&rng)) / (float)height;
    CameraDesc c = *cam;
    float3 dir = c.forward.xyz + sx * c.right.xyz + sy * c.up.xyz;  // unit length along the axis
    float3 origin = c.position.xyz;
    float lens_radius = c.forward.w;
    if (lens_radius > 0.0f) {
        float3 focus = origin + c.right.w * dir;
        float r = lens_radius * sqrt(rng_float(&rng)), phi = 2.0f * PI_F * rng_float(&rng);
        origin += r * cos(phi) * normalize(c.right.xyz) + r * sin(phi) * normalize(c.up.xyz);
        dir = (focus - origin) / c.right.w;  // still unit length along the axis
    }
    origin += c.position.w * dir;  // near clip: start on the plane at that axial distance
    float3 d = normalize(dir);
    float travelled = 0.0f;

    float3 thr = (float3)(1.0f);
    float3 direct = (float3)(0.0f);
    float4 pos = (float4)(0.0f), nrm = (float4)(0.0f), wgt = (float4)(0.0f);
    uint4 cut = (uint4)(CUT_NONE, CUT_NONE, 0u, 0u);
    Rng light_rng = rng_make(seed, light_pass, (uint)pixel, DOMAIN_NEE);
    float power = n_emitters > 0 ? total_power(emitters) : 0.0f;
    float last_pdf = 0.0f;  // the last bounce's BSDF pdf where its light was also sampled (0: none)
    for (int depth = 0; depth < max_bounces; ++depth) {  // a safety cap (kernels/contract.py)
        Hit h = intersect(&g, origin, d);
        if (h.surf == SURF_NONE) {  // the environment's light, weighted as emission hit (lights.cl)
            float p_light;
            float3 le = env_escape(emitters, n_emitters, d, &p_light);
            direct += thr * le * (last_pdf > 0.0f && p_light > 0.0f ? power_heuristic(last_pdf, p_light) : 1.0f);
            break;
        }
        float3 p = origin + h.t * d;
        travelled += h.t;
        Material m = hit_material(&g, surfaces, &h, p);
        float3 le = surface_emission(surfaces, h.surf);
        if (dot(d, h.ng) < 0.0f) {  // emitters shine from their front side
            float w = last_pdf > 0.0f && any(le > 0.0f) ? emission_weight(le, power, last_pdf, h.t, -dot(d, h.ng)) : 1.0f;
            direct += thr * le * w;
        }
        // The part the path takes: the diffuse part ends it at a measurement point.
        float3 n = dot(d, h.ng) < 0.0f ? h.ng : -h.ng;
        float3 ns = dot(d, h.ng) < 0.0f ? h.ns : -h.ns;
        float co = -dot(d, ns);
        float p_diffuse = part_choice(&m, fmax(co, 0.0f), PART_ALL).x;
        if (p_diffuse > 0.0f && (p_diffuse >= 1.0f || rng_float(&rng) < p_diffuse)) {
            float3 gw = diffuse_out(&m, co) / p_diffuse;
            pos = (float4)(p, 1.0f);
            float2 cover = disc_coverage(&g, p, n, h.tri, radius[gid], true, &rng, &cut);
            nrm = (float4)(n, cover.y);
            wgt = (float4)(thr * gw / PI_F, cover.x);
            if (nee) direct += thr * direct_light(&g, surfaces, emitters, emitter_cdf, n_emitters, p, n, ns, gw, &m,
                                                  &light_rng);
            break;
        }
        // The other parts: their direct light where they are not delta, then the bounce.
        int mask = PART_GLOSSY | PART_DELTA;
        float keep = 1.0f - p_diffuse;
        if (material_parts(&m) & PART_GLOSSY)  // photons are stored on diffuse parts only: this light is the light sample's alone
            direct += thr / keep * light_sample_parts(&g, emitters, emitter_cdf, n_emitters, &m, p, h.ng, h.ns, -d, mask,
                                                      true, &light_rng);
        BsdfSample b;
        if (!bsdf_sample(&m, h.ng, h.ns, d, mask, true, &rng, &b)) break;
        if (h.smooth && shading_bounce(d, b.dir, h.ng, h.ns, false) == 0.0f) break;
        last_pdf = b.delta ? 0.0f : b.pdf_fwd;
        thr *= b.weight / keep;
        d = b.dir;
        origin = p + (dot(b.dir, h.ng) > 0.0f ? h.ng : -h.ng) * ray_eps(&g, p);
    }
    mp_pos[gid] = pos;
    mp_nrm[gid] = nrm;
    mp_wgt[gid] = wgt;
    mp_dist[gid] = pos.w > 0.0f ? travelled : 0.0f;
    mp_cut[gid] = cut;
    __global double* ld = sum_at(batch_sums, width * height, gid, SUM_LD, 3);
    ld[0] += direct.x;
    ld[1] += direct.y;
    ld[2] += direct.z;
#ifdef SUM_LD2
    double lum = LUM_R * (double)direct.x + LUM_G * (double)direct.y + LUM_B * (double)direct.z;
    *sum_at(batch_sums, width * height, gid, SUM_LD2, 1) += lum * lum;
#endif
}
