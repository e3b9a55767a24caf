// The batch's per-pixel sums (kernels/contract.py, SumLayout): one block per sum, in the
// layout's order, each block holding its pixels' values in pixel order (1 or 3 doubles a
// pixel), so that the host reads every sum back as a contiguous array without a copy.
// SUM_<NAME> is the sum's offset in doubles per pixel, so its block starts at offset * n.
inline __global double* sum_at(__global double* sums, int n_pixels, int gid, int offset, int width) {
    return sums + (size_t)offset * (size_t)n_pixels + (size_t)gid * (size_t)width;
}

// Add a pass's value to a sum. On the first pass of a batch (`first`) store 0 + value instead,
// without reading the sum, so a batch needs no zero fill of its buffer first (a megapixel's
// sums are 100+ MB): 0 + value is what adding to a zeroed sum gives, bit for bit. The kernels
// that take `first` write every sum of the layout between them on a batch's first pass. A
// macro, so that `value` stays an expression: with -cl-mad-enable, `sum += a * b` fuses into
// one fma, and an inline function (or a select of 0 or the sum) changed the last bits.
#define add_to(sum, value, first) do {   \
        __global double* sum_ = (sum);    \
        if (first) *sum_ = 0.0 + (value); \
        else *sum_ += (value);            \
    } while (0)
