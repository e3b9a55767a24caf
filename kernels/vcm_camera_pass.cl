// Camera subpaths of the hybrid integrator: one work item per pixel and pass. The path
// starts with dVCM = N_L / p_cam (p_cam the pixel's solid-angle pdf, vcm_camera.cl),
// dVC = dVM = 0, and its quantities follow vcm_subpath.cl. At every hit:
//   1. emission seen (area emitters, front side): weight 1 / (1 + p_A dVCM + p_A cos/pi dVC),
//      p_A = pick / A the light sample's area pdf of that point (weight 1 on the first hit,
//      and for `lt`, where no other technique samples the path);
// where it leaves the scene, the environment's radiance, weighted 1 / (1 + pick pdf(w) dVCM +
// pick pdf(w) / (pi R^2) dVC) (environment.cl; SmallVCM's background light, the quantities
// as they stood at the last vertex);
// and at every non-specular hit (light tracing alone, `lt`, stops there: its camera path
// only collects emission seen directly or through specular surfaces):
//   2. next-event estimation (next_event);
//   3. connection to every stored vertex of light path gid mod N_L (connect_light_path);
//   4. merging (vcm) with the stored light vertices within r (merge_light_vertices), over
//      the share of the disc on x's own surface (eye_pass.cl, disc_coverage, for a uniform
//      kernel): where a concave corner's wall cuts the disc, no vertex of this surface lies
//      beyond it, so the estimate is renormalised to the covered share (without it a corner
//      comes out dark); only the vertices in the disc's covered part count
//      (inside_cut: no light through a wall from the same plane beyond it);
//   5. the bounce, Russian roulette, and the update of the quantities.
// Writes the pixel's camera-side radiance for the pass (w: the change of the merged part
// from radius r/2 to r, for the error estimate), and whether its ray hit anything.

// The camera vertex the techniques start from.
typedef struct {
    float3 p, wo;       // position; direction back along the camera path
    float3 ng, side;    // geometric normal as the shape defines it, and on the path's side
    float3 ns;          // shading normal
    Material m;
} CameraVertex;

inline BsdfEval camera_bsdf(const CameraVertex* x, float3 wi) {
    return bsdf_eval(&x->m, x->ng, x->ns, x->wo, wi, PART_ALL, true);
}

// One light sample, weighted 1 / (w_light + 1 + w_cam): w_light = p_bsdf / (pick p_direct)
// (0 for delta lights), w_cam = p_emit cos_x / (p_direct cos_l) (eta_vm + dVCM + dVC p_rev).
inline float3 next_event(const SceneGeom* g, __global const float4* emitters, __global const float* cdf,
                         int n_emitters, const CameraVertex* x, const SubPath* s, MisEtas eta, Rng* rng) {
    DirectSample ls;
    if (!sample_direct(g, emitters, cdf, n_emitters, x->p, rng, &ls)) return (float3)(0.0f);
    BsdfEval e = camera_bsdf(x, ls.wi);
    if (e.pdf_fwd <= 0.0f) return (float3)(0.0f);
    float3 off = dot(ls.wi, x->ng) > 0.0f ? x->ng : -x->ng;  // the side the light is on (transmission: the other)
    if (shadowed(g, x->p + off * ray_eps(g, x->p), &ls)) return (float3)(0.0f);
    float w_light = ls.delta ? 0.0f : e.pdf_fwd / (ls.pick * ls.direct_pdf);
    float w_cam = ls.emission_pdf * fabs(dot(ls.wi, x->ng)) / (ls.direct_pdf * ls.cos_light)
                * (eta.vm + s->dVCM + s->dVC * e.pdf_rev);
    return e.f * ls.li * (fabs(dot(ls.wi, x->ns)) / (ls.pick * ls.direct_pdf) / (w_light + 1.0f + w_cam));
}

// Connections to every stored vertex y of one light path, each weighted 1 / (w_light + 1 +
// w_cam): w_light = p_x->y (eta_vm + dVCM_y + dVC_y p_rev,y), w_cam = p_y->x (eta_vm + dVCM +
// dVC p_rev,x), the pdfs of sampling the other vertex, converted to area by cos / d^2.
inline float3 connect_light_path(const SceneGeom* g, __global const float4* surfaces,
                                 const CameraVertex* x, const SubPath* s, MisEtas eta, int last,
                                 __global const float4* lv_pos, __global const float4* lv_thr,
                                 __global const float4* lv_wo, __global const float4* lv_ng,
                                 __global const float4* lv_ns, __global const int* lv_prev,
                                 __global const float4* lv_tex) {
    float3 sum = (float3)(0.0f);
    for (int v = last; v >= 0; v = lv_prev[v]) {
        LightVertex y = load_light_vertex(lv_pos, lv_thr, lv_wo, lv_ng, lv_ns, (uint)v);
        float3 to = y.pos - x->p;
        float d2 = dot(to, to), dist = sqrt(d2);
        float3 dir = to / dist;
        BsdfEval ex = camera_bsdf(x, dir);
        if (ex.pdf_fwd <= 0.0f) continue;
        Material my = stored_material(surfaces, y.surf, lv_tex, (uint)v);
        BsdfEval ey = bsdf_eval(&my, y.ng, y.ns, y.wo, -dir, PART_ALL, false);
        if (ey.pdf_fwd <= 0.0f) continue;
        float3 y_side = dot(y.ng, dir) < 0.0f ? y.ng : -y.ng;  // y's normal on x's side
        float3 x_side = dot(x->ng, dir) > 0.0f ? x->ng : -x->ng;  // x's normal on y's side
        if (blocked_between(g, x->p + x_side * ray_eps(g, x->p), y.pos + y_side * ray_eps(g, y.pos))) continue;
        float cos_x = fabs(dot(dir, x->ng)), cos_y = fabs(dot(dir, y.ng));
        float w_light = ex.pdf_fwd * cos_y / d2 * (eta.vm + y.dVCM + y.dVC * ey.pdf_rev);
        float w_cam = ey.pdf_fwd * cos_x / d2 * (eta.vm + s->dVCM + s->dVC * ex.pdf_rev);
        float shade = fabs(dot(dir, x->ns)) * cos_y / d2;  // f_y y.thr is radiance per geometric area
        sum += y.thr * ex.f * ey.f * (shade / (w_light + 1.0f + w_cam));
    }
    return sum;
}

// Merging: the light vertices within r of x on a matching surface (normals within 45
// degrees, as SPPM's gather), found in the table entries of the cells its ball overlaps
// (ball_entries, spatial_hash.cl; positions in grid order, vcm_grid.cl), each weighted 1 / (w_light + 1 + w_cam), w_light = dVCM_y eta_vc + dVM_y
// p_fwd, w_cam = dVCM eta_vc + dVM p_rev. Returns the unnormalised sum f Phi within r, and
// within r/2 in `half_sum`, for the density estimate sum / (pi r^2 N_L).
inline float3 merge_light_vertices(const CameraVertex* x, const SubPath* s, MisEtas eta, float r2, uint4 cut,
                                   float inv_cell,
                                   uint mask, __global const uint* cell_start, __global const uint* cell_count,
                                   __global const float4* grid_pos, __global const float4* lv_pos,
                                   __global const float4* lv_thr, __global const float4* lv_wo,
                                   __global const float4* lv_ng, __global const float4* lv_ns, float3* half_sum) {
    float3 within = (float3)(0.0f);
    *half_sum = (float3)(0.0f);
    uint entries[8];
    int n_entries = ball_entries(x->p, sqrt(r2), inv_cell, mask, entries);
    bool uncut = (cut.x & cut.y) == CUT_NONE;  // inside_cut's own first test, kept out of the loop
    bool transmits = x->m.type == MAT_ROUGH_GLASS;
    // The candidate loop calls no builtin (dot3, geometry.cl): a call spills every live
    // vector register, and most candidates lie beyond r.
    for (int k = 0; k < n_entries; ++k) {
        uint begin = cell_start[entries[k]], end = begin + cell_count[entries[k]];
        for (uint j = begin; j < end; ++j) {
            float4 gp = grid_pos[j];
            float3 v = gp.xyz - x->p;
            float dd = dot3(v, v);
            if (dd >= r2 || !(uncut || inside_cut(cut, x->side, v, sqrt(r2)))) continue;
            LightVertex y = load_light_vertex(lv_pos, lv_thr, lv_wo, lv_ng, lv_ns, as_uint(gp.w));
            float3 y_side = dot(y.wo, y.ng) > 0.0f ? y.ng : -y.ng;
            // Another surface (eye_pass.cl); a surface that transmits takes light from either side.
            float match = transmits ? fabs(dot(y_side, x->side)) : dot(y_side, x->side);
            if (match <= NORMAL_MATCH_COS) continue;
            BsdfEval e = camera_bsdf(x, y.wo);
            if (e.pdf_fwd <= 0.0f) continue;
            float w_light = y.dVCM * eta.vc + y.dVM * e.pdf_fwd;
            float w_cam = s->dVCM * eta.vc + s->dVM * e.pdf_rev;
            float3 c3 = e.f * y.thr / (w_light + 1.0f + w_cam);
            within += c3;
            if (4.0f * dd < r2) *half_sum += c3;
        }
    }
    return within;
}

__kernel void vcm_camera_pass(
    SCENE_PARAMS,
    __global const float4* camera, int width, int height,
    ulong seed, uint pass, int max_bounces, uint n_light_paths,
    int connect, int merge, float eta_vcm, float radius,
    uint skip,  // stage timing only (contract.py HYBRID_SKIP): SKIP_NEE, SKIP_CONNECT, SKIP_MERGE
    __global const float4* lv_pos, __global const float4* lv_thr, __global const float4* lv_wo,
    __global const float4* lv_ng, __global const float4* lv_ns, __global const int* lv_prev,
    __global const int* path_last, __global const float4* lv_tex,
    float inv_cell, uint mask, __global const uint* cell_start, __global const uint* cell_count,
    __global const float4* grid_pos,
    __global float4* cam_out, __global int* cam_hit)
{
    int gid = get_global_id(0);
    if (gid >= width * height) return;
    SceneGeom g = SCENE_GEOM;
    Pinhole cam = pinhole(camera, width, height);
    Rng rng = rng_make(seed, pass, (uint)gid, DOMAIN_CAMERA_PATH);
    MisEtas eta = mis_etas(connect, merge, eta_vcm);
    float n_light = (float)n_light_paths;
    float power = n_emitters > 0 ? total_power(emitters) : 0.0f;
    float r2 = radius * radius;
    float merge_norm = 1.0f / (PI_F * r2 * n_light);

    SubPath s;
    float skipped;  // the first hit's distance from the pinhole is this more than the ray's
    s.dVCM = n_light / camera_ray(&cam, gid, &rng, &s.o, &s.d, &skipped);
    s.dVC = s.dVM = 0.0f;
    s.thr = (float3)(1.0f);
    float3 radiance = (float3)(0.0f);
    float merged_change = 0.0f;
    int hit_any = 0;
    for (int depth = 0; depth < max_bounces; ++depth) {
        Hit h = intersect(&g, s.o, s.d);
        if (h.surf == SURF_NONE) {  // 1. the environment seen: no distance or cosine (vcm_lights.cl)
            float p_light;
            float3 le = env_escape(emitters, n_emitters, s.d, &p_light);
            if (p_light > 0.0f) {
                float p_emit = p_light * env_position_pdf(emitters, n_emitters);
                radiance += s.thr * le * (depth > 0 && connect ? 1.0f / (1.0f + p_light * s.dVCM + p_emit * s.dVC) : 1.0f);
            }
            break;
        }
        hit_any = 1;
        float3 p = s.o + h.t * s.d;
        subpath_arrive(&s, &h, depth == 0 ? h.t + skipped : h.t);
        CameraVertex x = {p, -s.d, h.ng, dot(s.d, h.ng) < 0.0f ? h.ng : -h.ng, h.ns, hit_material(&g, surfaces, &h, p)};
        float3 le = surface_emission(surfaces, h.surf);

        // 1. Emission seen.
        if (dot(s.d, h.ng) < 0.0f && any(le > 0.0f)) {
            float w = 1.0f;
            if (depth > 0 && connect) {
                float p_a = hit_emitter_pdf_area(le, power);
                w = 1.0f / (1.0f + p_a * s.dVCM + p_a * fabs(dot(s.d, h.ng)) / PI_F * s.dVC);
            }
            radiance += s.thr * le * w;
        }
        int parts = PART_ALL;  // the parts the bounce may take
        if (!is_delta(&x.m)) {
            // Light tracing alone covers every non-delta part: the camera path goes on through a delta one only.
            if (!connect && !merge) {
                parts = PART_DELTA;
                if (!(material_parts(&x.m) & PART_DELTA)) break;
            }
            // 2. Next-event estimation.
            if (connect && n_emitters > 0 && !(skip & SKIP_NEE))
                radiance += s.thr * next_event(&g, emitters, emitter_cdf, n_emitters, &x, &s, eta, &rng);
            // 3. Connections to the vertices of one light path.
            if (connect && n_light_paths > 0 && !(skip & SKIP_CONNECT))
                radiance += s.thr * connect_light_path(&g, surfaces, &x, &s, eta,
                                                       path_last[(uint)gid % n_light_paths], lv_pos, lv_thr,
                                                       lv_wo, lv_ng, lv_ns, lv_prev, lv_tex);
            // 4. Merging with the light vertices within r.
            if (merge && !(skip & SKIP_MERGE)) {
                float3 half_sum;
                uint4 cut = (uint4)(CUT_NONE, CUT_NONE, 0u, 0u);  // the whole disc
                float3 m = merge_light_vertices(&x, &s, eta, r2, cut, inv_cell, mask, cell_start, cell_count, grid_pos,
                                                lv_pos, lv_thr, lv_wo, lv_ng, lv_ns, &half_sum);
                if (any(m != 0.0f)) {  // the share of the discs on x's own surface (eye_pass.cl)
                    float2 cover = fmax(disc_coverage(&g, x.p, x.side, h.tri, radius, false, &rng, &cut), MIN_COVERAGE);
                    if ((cut.x & cut.y) != CUT_NONE)  // a wall cuts the disc: only its covered part counts
                        m = merge_light_vertices(&x, &s, eta, r2, cut, inv_cell, mask, cell_start, cell_count,
                                                 grid_pos, lv_pos, lv_thr, lv_wo, lv_ng, lv_ns, &half_sum);
                    m /= cover.x;
                    half_sum /= cover.y;
                }
                radiance += s.thr * m * merge_norm;
                merged_change += luminance(s.thr * (m - 4.0f * half_sum)) * merge_norm;
            }
        }
        // 5. Bounce, Russian roulette, and the quantities' update.
        if (!subpath_bounce(&g, &s, &h, p, &x.m, parts, false, eta, &rng)) break;
    }
    cam_out[gid] = (float4)(radiance, merged_change);
    cam_hit[gid] = hit_any;
}
