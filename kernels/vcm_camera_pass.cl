// Camera subpaths of the hybrid integrator: one work item per pixel and pass. The path
// starts with dVCM = N_L / p_cam (p_cam the pixel's solid-angle pdf, vcm_camera.cl),
// dVC = dVM = 0, and its quantities follow the rules of vcm_light_pass.cl. At every hit:
//   1. emission seen (area emitters, front side): weight 1 / (1 + p_A dVCM + p_A cos/pi dVC),
//      p_A = pick / A the light sample's area pdf of that point (1 on the first hit, where
//      no other technique samples the path);
// and at every non-specular hit (light tracing alone, `lt`, stops there: its camera path
// only collects emission seen directly or through specular surfaces):
//   2. next-event estimation: weight 1 / (w_light + 1 + w_cam),
//      w_light = p_bsdf / (pick p_direct) (0 for delta lights),
//      w_cam = p_emit cos_x / (p_direct cos_l) (eta_vm + dVCM + dVC p_rev);
//   3. connection to every stored vertex y of light path gid mod N_L: weight
//      1 / (w_light + 1 + w_cam), w_light = p_x->y,A (eta_vm + dVCM_y + dVC_y p_rev,y),
//      w_cam = p_y->x,A (eta_vm + dVCM + dVC p_rev,x), area pdfs from solid angle by cos / d^2;
//   4. merging (vcm) with every stored light vertex within r on a matching surface (normals
//      within 45 degrees, as SPPM's gather): the density estimate
//      f Phi / (pi r^2 N_L) weighted 1 / (w_light + 1 + w_cam), w_light = dVCM_y eta_vc +
//      dVM_y p_fwd, w_cam = dVCM eta_vc + dVM p_rev. The same vertices within r/2, at that
//      radius's normalisation, give the change of the merged estimate between the radii
//      (the error estimate's bias term; worker/integrators/connect_merge.py);
//   5. the bounce, Russian roulette, and the update of the quantities.
// Writes the pixel's camera-side radiance for the pass (w: the merged change), and whether
// its camera ray hit anything (pixels that see nothing carry no error estimate).

__kernel void vcm_camera_pass(
    __global const float4* tri_v0, __global const float4* tri_e1, __global const float4* tri_e2,
    __global const float4* tri_nrm,
    __global const float4* node_lo, __global const float4* node_hi, int n_nodes,
    __global const float4* spheres, __global const int* sphere_surf, int n_spheres,
    __global const float4* surf_a, __global const float4* surf_b,
    __global const float4* emitters, __global const float* emitter_cdf, int n_emitters,
    __global const float4* camera, int width, int height,
    ulong seed, uint pass, int max_bounces, uint n_light_paths,
    int connect, int merge, float eta_vcm, float radius,
    __global const float4* lv_pos, __global const float4* lv_thr, __global const float4* lv_wo,
    __global const float4* lv_ng, __global const float4* lv_ns, __global const int* lv_prev,
    __global const int* path_last,
    float inv_cell, uint mask, __global const uint* cell_start, __global const uint* cell_count,
    __global const uint* sorted,
    __global float4* cam_out, __global int* cam_hit)
{
    int gid = get_global_id(0);
    if (gid >= width * height) return;
    SceneGeom g = {tri_v0, tri_e1, tri_e2, tri_nrm, node_lo, node_hi, spheres, sphere_surf, n_nodes, n_spheres};
    Pinhole cam = pinhole(camera, width, height);
    Rng rng = rng_make(seed, pass, (uint)gid, DOMAIN_CAMERA_PATH);
    float eta_vm = merge ? eta_vcm : 0.0f, eta_vc = connect ? 1.0f / eta_vcm : 0.0f;
    float n_light = (float)n_light_paths;
    float power = n_emitters > 0 ? total_power(emitters) : 0.0f;
    float r2 = radius * radius;
    float merge_norm = 1.0f / (PI_F * r2 * n_light);

    float3 o, d;
    float dVCM = n_light / camera_ray(&cam, gid, &rng, &o, &d), dVC = 0.0f, dVM = 0.0f;
    float3 thr = (float3)(1.0f), radiance = (float3)(0.0f);
    float merged_change = 0.0f;
    int hit_any = 0;
    for (int depth = 0; depth < max_bounces; ++depth) {
        Hit h = intersect(&g, o, d);
        if (h.surf == SURF_NONE) break;
        hit_any = 1;
        float3 p = o + h.t * d;
        float cos_in = fabs(dot(d, h.ng));
        dVCM *= h.t * h.t / cos_in;
        dVC /= cos_in;
        dVM /= cos_in;
        float4 sa = surf_a[h.surf], sb = surf_b[h.surf];
        int type = as_int(sa.w);
        float3 wo = -d;
        float3 side = dot(wo, h.ng) > 0.0f ? h.ng : -h.ng;  // geometric normal on the path's side
        float3 ns = dot(side, h.ns) > 0.0f ? h.ns : -h.ns;

        // 1. Emission seen.
        if (dot(d, h.ng) < 0.0f && any(sb.xyz > 0.0f)) {
            float w = 1.0f;
            if (depth > 0 && connect) {
                float p_a = hit_emitter_pdf_area(sb.xyz, power);
                w = 1.0f / (1.0f + p_a * dVCM + p_a * cos_in / PI_F * dVC);
            }
            radiance += thr * sb.xyz * w;
        }
        if (!is_delta(type)) {
            if (!connect && !merge) break;
            // 2. Next-event estimation.
            DirectSample ls;
            if (connect && n_emitters > 0 && sample_direct(emitters, emitter_cdf, n_emitters, p, &rng, &ls)) {
                BsdfEval e = bsdf_eval(type, sb.w, sa.xyz, h.ng, h.ns, wo, ls.wi);
                if (e.pdf_fwd > 0.0f) {
                    Hit block = intersect_within(&g, p + side * ray_eps(p), ls.wi, ls.dist);
                    if (block.surf == SURF_NONE) {
                        float w_light = ls.delta ? 0.0f : e.pdf_fwd / (ls.pick * ls.direct_pdf);
                        float w_cam = ls.emission_pdf * fabs(dot(ls.wi, h.ng)) / (ls.direct_pdf * ls.cos_light)
                                    * (eta_vm + dVCM + dVC * e.pdf_rev);
                        radiance += thr * e.f * ls.li * (dot(ls.wi, ns) / (ls.pick * ls.direct_pdf)
                                                         / (w_light + 1.0f + w_cam));
                    }
                }
            }
            // 3. Connections to the vertices of one light path.
            if (connect && n_light_paths > 0) {
                for (int v = path_last[(uint)gid % n_light_paths]; v >= 0; v = lv_prev[v]) {
                    LightVertex y = load_light_vertex(lv_pos, lv_thr, lv_wo, lv_ng, lv_ns, (uint)v);
                    float3 to = y.pos - p;
                    float d2 = dot(to, to), dist = sqrt(d2);
                    float3 dir = to / dist;
                    BsdfEval ex = bsdf_eval(type, sb.w, sa.xyz, h.ng, h.ns, wo, dir);
                    if (ex.pdf_fwd <= 0.0f) continue;
                    float4 ya = surf_a[y.surf];
                    BsdfEval ey = bsdf_eval(as_int(ya.w), surf_b[y.surf].w, ya.xyz, y.ng, y.ns, y.wo, -dir);
                    if (ey.pdf_fwd <= 0.0f) continue;
                    Hit block = intersect_within(&g, p + side * ray_eps(p), dir, dist - 2.0f * ray_eps(y.pos));
                    if (block.surf != SURF_NONE) continue;
                    float cos_x = fabs(dot(dir, h.ng)), cos_y = fabs(dot(dir, y.ng));
                    float w_light = ex.pdf_fwd * cos_y / d2 * (eta_vm + y.dVCM + y.dVC * ey.pdf_rev);
                    float w_cam = ey.pdf_fwd * cos_x / d2 * (eta_vm + dVCM + dVC * ex.pdf_rev);
                    float shade = fabs(dot(dir, h.ns)) * cos_y / d2;  // f_y y.thr is radiance per geometric area
                    radiance += thr * y.thr * ex.f * ey.f * (shade / (w_light + 1.0f + w_cam));
                }
            }
            // 4. Merging with the light vertices within r (the 8 grid cells of spatial_hash.cl).
            if (merge) {
                float3 within = (float3)(0.0f), within_half = (float3)(0.0f);
                QueryCells q = query_cells(p, inv_cell);
                for (int k = 0; k < 8; ++k) {
                    int3 cell = query_cell(q, k);
                    uint c = cell_hash(cell, mask), begin = cell_start[c], end = begin + cell_count[c];
                    for (uint j = begin; j < end; ++j) {
                        uint i = sorted[j];
                        float3 y_pos = lv_pos[i].xyz;
                        if (any(cell_of(y_pos, inv_cell) != cell)) continue;
                        float3 v = y_pos - p;
                        float dd = dot(v, v);
                        if (dd >= r2) continue;
                        LightVertex y = load_light_vertex(lv_pos, lv_thr, lv_wo, lv_ng, lv_ns, i);
                        float3 y_side = dot(y.wo, y.ng) > 0.0f ? y.ng : -y.ng;
                        if (dot(y_side, side) <= NORMAL_MATCH_COS) continue;  // another surface (eye_pass.cl)
                        BsdfEval e = bsdf_eval(type, sb.w, sa.xyz, h.ng, h.ns, wo, y.wo);
                        if (e.pdf_fwd <= 0.0f) continue;
                        float w_light = y.dVCM * eta_vc + y.dVM * e.pdf_fwd;
                        float w_cam = dVCM * eta_vc + dVM * e.pdf_rev;
                        float3 c3 = e.f * y.thr / (w_light + 1.0f + w_cam);
                        within += c3;
                        if (4.0f * dd < r2) within_half += c3;
                    }
                }
                radiance += thr * within * merge_norm;
                merged_change += luminance(thr * (within - 4.0f * within_half)) * merge_norm;
            }
        }
        // 5. Bounce, Russian roulette, and the quantities' update.
        BsdfSample s;
        if (!bsdf_sample(type, sb.w, sa.xyz, h.ng, h.ns, d, &rng, &s)) break;
        float3 w = s.weight;
        if (h.smooth) w *= shading_bounce(d, s.dir, h.ng, h.ns, false);
        float survive = fmin(1.0f, fmax(w.x, fmax(w.y, w.z)));
        if (rng_float(&rng) >= survive) break;
        thr *= w / survive;
        float cos_out = fabs(dot(s.dir, h.ng));
        if (s.delta) {
            dVCM = 0.0f;
            dVC *= cos_out;
            dVM *= cos_out;
        } else {
            dVC = cos_out / s.pdf_fwd * (dVC * s.pdf_rev + dVCM + eta_vm);
            dVM = cos_out / s.pdf_fwd * (dVM * s.pdf_rev + dVCM * eta_vc + 1.0f);
            dVCM = 1.0f / s.pdf_fwd;
        }
        d = s.dir;
        o = p + (dot(d, h.ng) > 0.0f ? h.ng : -h.ng) * ray_eps(p);
    }
    cam_out[gid] = (float4)(radiance, merged_change);
    cam_hit[gid] = hit_any;
}
