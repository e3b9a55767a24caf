// The batch's per-pixel sums (kernels/contract.py, SumLayout): one block per sum, in the
// layout's order, each block holding its pixels' values in pixel order (1 or 3 doubles a
// pixel), so that the host reads every sum back as a contiguous array without a copy.
// SUM_<NAME> is the sum's offset in doubles per pixel, so its block starts at offset * n.
inline __global double* sum_at(__global double* sums, int n_pixels, int gid, int offset, int width) {
    return sums + (size_t)offset * (size_t)n_pixels + (size_t)gid * (size_t)width;
}
