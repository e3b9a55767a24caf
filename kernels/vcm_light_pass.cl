// Light subpaths of the hybrid integrator (vertex connection and merging, Georgiev et al.
// 2012): one work item per light path. Per path:
//   1. emit from a light chosen by power, with the initial MIS quantities (vcm_lights.cl);
//   2. at every hit, turn the quantities to the area measure there (vcm_subpath.cl);
//   3. at a non-specular hit, store the vertex (for connections and merging; its throughput
//      as the flux per geometric area a BSDF about the shading normal sees, as photons) and
//   4. connect it to the camera: a light-tracing splat to whichever pixel it projects to,
//      weighted 1 / (1 + p_cam / N_L (eta_vm + dVCM + dVC p_rev)), p_cam the area pdf of the
//      pixel's camera ray finding the vertex (vcm_camera.cl); light tracing alone
//      (`connect` off) is the only technique for its paths and weighs 1;
//   5. bounce, Russian roulette, and the quantities' update (vcm_subpath.cl).
//
// Stored vertices get slots from an atomic counter, so each also records the slot of its
// path's previous stored vertex (a list from path_last[path] back to -1) and a key
// (path << 12 | bounce): the camera pass visits a path's vertices by the list and a grid
// cell's vertices sorted by key, so the order of float sums never depends on the slots.
// Splats are summed in fixed point with 64-bit integer atomics, in units of the scene's radiance scale
// (`splat_scale`; worker/scene_arrays.py radiance_scale, contract.py SPLAT_FRACTION_BITS).

typedef struct {
    float3 pos, thr, wo, ng, ns;  // wo: back along the light path
    int surf;
    float dVCM, dVC, dVM;
} LightVertex;

inline LightVertex load_light_vertex(__global const float4* lv_pos, __global const float4* lv_thr,
                                     __global const float4* lv_wo, __global const float4* lv_ng,
                                     __global const float4* lv_ns, uint i) {
    float4 p = lv_pos[i], t = lv_thr[i], w = lv_wo[i], n = lv_ng[i], s = lv_ns[i];
    LightVertex v = {p.xyz, t.xyz, w.xyz, n.xyz, s.xyz, as_int(p.w), t.w, w.w, n.w};
    return v;
}

// Add rgb radiance to a pixel's fixed-point splat accumulator (`scale` units a radiance,
// kernels/contract.py SPLAT_FRACTION_BITS).
inline void splat(__global volatile long* acc, int pixel, float3 value, float scale) {
    __global volatile long* a = acc + 3 * pixel;
    atom_add(a, convert_long_sat_rte(value.x * scale));
    atom_add(a + 1, convert_long_sat_rte(value.y * scale));
    atom_add(a + 2, convert_long_sat_rte(value.z * scale));
}

__kernel void vcm_light_pass(
    SCENE_PARAMS,
    __global const float4* camera, int width, int height,
    ulong seed, uint pass, int max_bounces, uint n_paths, uint capacity,
    int connect, int merge,        // the techniques on (bpt: connect; vcm: both; lt: neither)
    float eta_vcm,                 // pi r^2 N_L of this pass
    int store,                     // 1: keep the vertices (bpt, vcm)
    uint skip,                     // stage timing only (contract.py HYBRID_SKIP): SKIP_SPLAT
    __global float4* lv_pos, __global float4* lv_thr, __global float4* lv_wo, __global float4* lv_ng,
    __global float4* lv_ns, __global ulong* lv_key, __global int* lv_prev, __global int* path_last,
    __global float4* lv_tex,       // textured materials' values (textures.cl, store_textured)
    __global volatile uint* lv_count,
    __global volatile long* splats,  // per pixel rgb, fixed point
    float splat_scale)               // fixed-point units per unit of radiance
{
    uint path = (uint)get_global_id(0);
    if (path >= n_paths) return;
    if (n_emitters == 0) { path_last[path] = -1; return; }
    SceneGeom g = SCENE_GEOM;
    Pinhole cam = pinhole(camera, width, height);
    Rng rng = rng_make(seed, pass, path, DOMAIN_LIGHT_PATH);
    MisEtas eta = mis_etas(connect, merge, eta_vcm);
    float n_light = (float)n_paths;

    // 1. Emission.
    Emission em = sample_emission(&g, emitters, emitter_cdf, n_emitters, &rng);
    SubPath s = {em.o, em.d, em.flux, em.dVCM, em.dVC, em.dVC * eta.vc};
    int prev = -1;

    for (int bounce = 0; bounce < max_bounces; ++bounce) {
        Hit h = intersect(&g, s.o, s.d);
        if (h.surf == SURF_NONE) break;
        float3 p = s.o + h.t * s.d;
        // 2. The quantities in the area measure at the hit.
        subpath_arrive(&s, &h, bounce > 0 || !em.infinite ? h.t : 0.0f);
        Material m = hit_material(&g, surfaces, &h, p);
        if (!is_delta(&m)) {
            float3 arriving = h.smooth ? s.thr * shading_arrival(s.d, h.ng, h.ns) : s.thr;
            // 3. Store the vertex.
            if (store) {
                uint slot = atomic_inc(lv_count);
                if (slot < capacity) {  // the host re-runs the pass with more room on overflow
                    lv_pos[slot] = (float4)(p, as_float(h.surf));
                    lv_thr[slot] = (float4)(arriving, s.dVCM);
                    lv_wo[slot] = (float4)(-s.d, s.dVC);
                    lv_ng[slot] = (float4)(h.ng, s.dVM);
                    lv_ns[slot] = (float4)(h.ns, 0.0f);
                    if (m.flags & MF_TEXTURED) store_textured(lv_tex, slot, &m);
                    lv_key[slot] = ((ulong)path << 12) | (ulong)bounce;
                    lv_prev[slot] = prev;
                    prev = (int)slot;
                }
            }
            // 4. Light tracing: connect to the camera.
            Projection pr;
            if (!(skip & SKIP_SPLAT) && project(&cam, p, &rng, &pr)) {
                BsdfEval e = bsdf_eval(&m, h.ng, h.ns, -s.d, pr.to_camera, PART_ALL, false);
                float3 side = dot(pr.to_camera, h.ng) > 0.0f ? h.ng : -h.ng;
                if (e.pdf_fwd > 0.0f
                    && !occluded(&g, p + side * ray_eps(&g, p), pr.to_camera, pr.visible)) {
                    // Radiance f * arriving toward the camera, over the solid angle cos_y / d^2
                    // of the surface, times the pixel's importance: p_cam itself.
                    float p_cam = pr.importance * fabs(dot(pr.to_camera, h.ng)) / (pr.dist * pr.dist);
                    float w = connect ? 1.0f / (1.0f + p_cam / n_light * (eta.vm + s.dVCM + s.dVC * e.pdf_rev))
                                      : 1.0f;
                    splat(splats, pr.pixel, arriving * e.f * (p_cam / n_light * w), splat_scale);
                }
            }
        }
        // 5. Bounce, Russian roulette, and the quantities' update.
        if (!subpath_bounce(&g, &s, &h, p, &m, PART_ALL, true, eta, &rng)) break;
    }
    if (store) path_last[path] = prev;
}
