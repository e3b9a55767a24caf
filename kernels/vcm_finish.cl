// End of a hybrid pass: per pixel, the pass's radiance is the camera side (vcm_camera_pass.cl)
// plus the light-tracing splats (fixed point, vcm_light_pass.cl). It adds to the batch's
// per-pixel sums (kernels/contract.py layout): C the radiance, and where the layout has
// them, Y2 the squared luminance of the pass's sample (the variance of the per-pass
// samples), H the passes whose camera ray hit a surface, and Mh, Mh2 the change of the merged estimate from radius r/2 to r and its
// square (the bias term). The splat accumulators are cleared for the next pass.

__kernel void vcm_finish(int n_pixels, __global const float4* cam_out, __global const int* cam_hit,
                         __global long* splats, __global double* batch_sums) {
    int gid = get_global_id(0);
    if (gid >= n_pixels) return;
    float4 c = cam_out[gid];
    __global long* s = splats + 3 * gid;
    double3 v = convert_double3(c.xyz) + (double3)((double)s[0], (double)s[1], (double)s[2]) / SPLAT_SCALE;
    s[0] = s[1] = s[2] = 0;
    __global double* rec = batch_sums + (size_t)gid * SUM_STRIDE;
    rec[SUM_C] += v.x;
    rec[SUM_C + 1] += v.y;
    rec[SUM_C + 2] += v.z;
#ifdef SUM_Y2
    double y = LUM_R * v.x + LUM_G * v.y + LUM_B * v.z;
    rec[SUM_Y2] += y * y;
    rec[SUM_H] += (double)cam_hit[gid];
#endif
#ifdef SUM_MH
    rec[SUM_MH] += (double)c.w;
    rec[SUM_MH2] += (double)c.w * (double)c.w;
#endif
}
