// End of a hybrid pass: per pixel, the pass's radiance is the camera side (vcm_camera_pass.cl)
// plus the light-tracing splats (fixed point, splat_scale units a radiance: vcm_light_pass.cl).
// It adds to the batch's per-pixel sums (kernels/contract.py layout, sums.cl): C the radiance,
// and where the layout has them, Y2 the squared luminance of the pass's sample (the variance of
// the per-pass samples), H the passes whose camera ray hit a surface, and Mh, Mh2 the change of
// the merged estimate from radius r/2 to r and its square (the bias term). The splat
// accumulators are cleared for the next pass.

__kernel void vcm_finish(int n_pixels, __global const float4* cam_out, __global const int* cam_hit,
                         __global long* splats, float splat_scale, __global double* batch_sums) {
    int gid = get_global_id(0);
    if (gid >= n_pixels) return;
    float4 c = cam_out[gid];
    __global long* s = splats + 3 * gid;
    double3 v = convert_double3(c.xyz) + (double3)((double)s[0], (double)s[1], (double)s[2]) / (double)splat_scale;
    s[0] = s[1] = s[2] = 0;
    __global double* rgb = sum_at(batch_sums, n_pixels, gid, SUM_C, 3);
    rgb[0] += v.x;
    rgb[1] += v.y;
    rgb[2] += v.z;
#ifdef SUM_Y2
    double y = LUM_R * v.x + LUM_G * v.y + LUM_B * v.z;
    *sum_at(batch_sums, n_pixels, gid, SUM_Y2, 1) += y * y;
    *sum_at(batch_sums, n_pixels, gid, SUM_H, 1) += (double)cam_hit[gid];
#endif
#ifdef SUM_MH
    *sum_at(batch_sums, n_pixels, gid, SUM_MH, 1) += (double)c.w;
    *sum_at(batch_sums, n_pixels, gid, SUM_MH2, 1) += (double)c.w * (double)c.w;
#endif
}
