// Photon lookup structures, rebuilt every pass, and the gather at measurement points.
//
// Both use a uniform grid of cell size 2 * (largest current radius), hashed into a table
// (dissertation 10.2.2). A query visits the table entries of the cells that the bounding
// box of its ball (radius r about the point) overlaps: at most 2 cells per axis, 8 in all,
// as r <= cell/2. Each distinct entry is visited once, so two query cells that collide in
// the table never count a photon twice; a photon of some other cell that shares an entry
// lies outside the box, farther than r, so the distance test alone decides.
//
// Stochastic spatial hashing (dissertation ch. 10, digest 8): each table entry keeps ONE
// of the n photons hashed to it, chosen uniformly at random by an atomic minimum over
// random keys (not a racy last-writer-wins store), and that photon stands for all n: its
// flux is multiplied by n and n is added to M. In expectation this is the full sum.
//
// Exact gathering counting-sorts all photons by entry (their records moved to their slots,
// then sorted within each entry), splits them into the gather's arrays, and visits every
// photon of the query's entries. Its cells are split GRID_ROW_SPLIT ways along x
// (kernels/contract.py), and a row's consecutive cells take consecutive entries
// (cell_hash), so the photons of the cells a query's box overlaps along x lie in one run:
// a query reads at most 4 runs (ball_rows), not 8 cells, and visits the photons of a box
// 2r + 2R / GRID_ROW_SPLIT wide along x rather than up to 4R (R the largest radius).

// A grid's cell, `split` times finer along x: the exact grid's rows (ball_rows) split it
// GRID_ROW_SPLIT ways; the other grids' builds pass 1 (cell_of).
inline int3 split_cell_of(float3 p, float inv_cell, uint split) {
    return convert_int3_rtn((float3)(p.x * (float)split, p.y, p.z) * inv_cell);
}

inline int3 cell_of(float3 p, float inv_cell) { return split_cell_of(p, inv_cell, 1u); }

// A cell's table entry: its row's (y, z) hashed, plus x, so that a row's consecutive cells
// take consecutive entries, and the exact grid holds their photons in one run (ball_rows).
inline uint cell_hash(int3 c, uint mask) {
    ulong h = (ulong)(uint)c.y * 0xC2B2AE3D27D4EB4FUL ^ (ulong)(uint)c.z * 0x165667B19E3779F9UL;
    return ((uint)mix64(h) + (uint)c.x) & mask;
}

// --- stochastic hash: selection by atomic minimum, then the winner writes its payload
__kernel void hash_select(uint n, __global const float4* ph_pos, __global const ulong* ph_key,
                          float inv_cell, uint mask,
                          __global volatile ulong* tab_key, __global volatile uint* tab_count) {
    uint i = get_global_id(0);
    if (i >= n) return;
    uint h = cell_hash(cell_of(ph_pos[i].xyz, inv_cell), mask);
    atom_min(&tab_key[h], ph_key[i]);
    atomic_inc(&tab_count[h]);
}

__kernel void hash_store(uint n, __global const float4* ph_pos, __global const float4* ph_flux,
                         __global const uint2* ph_dirs,
                         __global const ulong* ph_key, float inv_cell, uint mask,
                         __global const ulong* tab_key, __global float4* tab_pos, __global float4* tab_flux,
                         __global uint2* tab_dirs) {
    uint i = get_global_id(0);
    if (i >= n) return;
    uint h = cell_hash(cell_of(ph_pos[i].xyz, inv_cell), mask);
    if (tab_key[h] == ph_key[i]) {  // keys are unique: exactly one photon per entry matches
        tab_pos[h] = ph_pos[i];
        tab_flux[h] = ph_flux[i];
        tab_dirs[h] = ph_dirs[i];
    }
}

// --- exact grid: count per entry, exclusive scan, scatter photon indices
__kernel void grid_count(uint n, __global const float4* ph_pos, float inv_cell, uint split, uint mask,
                         __global volatile uint* cell_count) {
    uint i = get_global_id(0);
    if (i >= n) return;
    atomic_inc(&cell_count[cell_hash(split_cell_of(ph_pos[i].xyz, inv_cell, split), mask)]);
}

// A single work item: the scan is memory-bound and tiny next to tracing.
__kernel void grid_scan(uint entries, __global const uint* cell_count, __global uint* cell_start,
                        __global uint* cell_fill) {
    if (get_global_id(0) != 0) return;  // one work item scans (launched in a whole work group)
    uint sum = 0;
    for (uint h = 0; h < entries; ++h) {
        cell_start[h] = sum;
        cell_fill[h] = sum;
        sum += cell_count[h];
    }
}

__kernel void grid_scatter(uint n, __global const float4* ph_pos, float inv_cell, uint split, uint mask,
                           __global volatile uint* cell_fill, __global uint* sorted) {
    uint i = get_global_id(0);
    if (i >= n) return;
    uint h = cell_hash(split_cell_of(ph_pos[i].xyz, inv_cell, split), mask);
    sorted[atomic_inc(&cell_fill[h])] = i;
}

// The photons' grid: grid_scatter with each photon's whole record moved to its slot, read
// in trace order. A record is one 64-byte line (PhotonSlot), so the scatter writes one
// random line a photon rather than one per field. grid_sort_slots and grid_permute then
// reach only the slots of one entry, which lie together.
typedef struct {
    float4 pos;    // xyz, w: count
    float4 flux;
    uint2 dirs;    // packed incoming direction and surface normal
    ulong key;
    uint4 pad;     // to a 64-byte line
} PhotonSlot;

__kernel void grid_scatter_photons(uint n, __global const float4* ph_pos, __global const float4* ph_flux,
                                   __global const uint2* ph_dirs, __global const ulong* ph_key, float inv_cell,
                                   uint split, uint mask, __global volatile uint* cell_fill, __global PhotonSlot* slots) {
    uint i = get_global_id(0);
    if (i >= n) return;
    float4 pos = ph_pos[i];
    uint j = atomic_inc(&cell_fill[cell_hash(split_cell_of(pos.xyz, inv_cell, split), mask)]);
    slots[j] = (PhotonSlot){pos, ph_flux[i], ph_dirs[i], ph_key[i], (uint4)(0)};
}

// The scatter fills each entry in whatever order the atomics ran (and photon slots came
// from an atomic counter too), so the float sums of a gather would differ in the last bits
// from run to run. Heap-sorting each entry by the keys, which are a function of (seed,
// pass, path, bounce) and unique, makes the same seed give the same image, bit for bit.
// HEAP_SORT(n, LESS, SWAP) sorts positions 0 .. n-1 ascending, LESS(i, j) and SWAP(i, j)
// comparing and swapping the items at two positions.
#define SIFT_DOWN(ROOT, END, LESS, SWAP)                         \
    {                                                            \
        int r_ = (ROOT);                                         \
        while (2 * r_ + 1 < (END)) {                             \
            int c_ = 2 * r_ + 1;                                 \
            if (c_ + 1 < (END) && LESS(c_, c_ + 1)) ++c_;        \
            if (!LESS(r_, c_)) break;                            \
            SWAP(r_, c_)                                         \
            r_ = c_;                                             \
        }                                                        \
    }
#define HEAP_SORT(N, LESS, SWAP)                                 \
    {                                                            \
        int n_ = (N);                                            \
        for (int s_ = n_ / 2 - 1; s_ >= 0; --s_) SIFT_DOWN(s_, n_, LESS, SWAP) \
        for (int e_ = n_ - 1; e_ > 0; --e_) {                    \
            SWAP(0, e_)                                          \
            SIFT_DOWN(0, e_, LESS, SWAP)                         \
        }                                                        \
    }

// Entry indices (the light-vertex grid, vcm_grid.cl) by the keys they point to.
__kernel void grid_sort(uint entries, __global const uint* cell_start, __global const uint* cell_count,
                        __global uint* sorted, __global const ulong* ph_key) {
    uint h = get_global_id(0);
    if (h >= entries) return;
    __global uint* a = sorted + cell_start[h];
#define INDEX_LESS(i, j) (ph_key[a[i]] < ph_key[a[j]])
#define INDEX_SWAP(i, j) { uint t = a[i]; a[i] = a[j]; a[j] = t; }
    HEAP_SORT((int)cell_count[h], INDEX_LESS, INDEX_SWAP)
#undef INDEX_LESS
#undef INDEX_SWAP
}

// The photon records themselves, in place: an entry's slots are one run of lines.
__kernel void grid_sort_slots(uint entries, __global const uint* cell_start, __global const uint* cell_count,
                              __global PhotonSlot* slots) {
    uint h = get_global_id(0);
    if (h >= entries) return;
    __global PhotonSlot* a = slots + cell_start[h];
#define SLOT_LESS(i, j) (a[i].key < a[j].key)
#define SLOT_SWAP(i, j) { PhotonSlot t = a[i]; a[i] = a[j]; a[j] = t; }
    HEAP_SORT((int)cell_count[h], SLOT_LESS, SLOT_SWAP)
#undef SLOT_LESS
#undef SLOT_SWAP
}

// The photons in the gather's arrays, so that a query's distance test reads only positions
// (consecutive for an entry), with the packed directions unpacked once here rather than at
// every query that finds them.
__kernel void grid_permute(uint n, __global const PhotonSlot* slots, __global float4* grid_pos,
                           __global float4* grid_flux, __global float4* grid_in, __global float4* grid_nrm) {
    uint j = get_global_id(0);
    if (j >= n) return;
    PhotonSlot s = slots[j];
    grid_pos[j] = s.pos;
    grid_flux[j] = s.flux;
    grid_in[j] = (float4)(unpack_dir(s.dirs.x), 0.0f);
    grid_nrm[j] = (float4)(unpack_dir(s.dirs.y), 0.0f);
}

// --- gather: per pixel, the photons within its radius of this pass's measurement point
//
// Density estimation with the smooth kernel of dissertation eq. 6.34,
//     K(t) = 1 - 6t^5 + 15t^4 - 10t^3,   normalised by k1 r^2, k1 = 2 pi / 7,
// which vanishes at t = 1 with its first two derivatives, so the flux and its Laplacian
// can both be estimated from the same photons (section 6.4). The Laplacian is taken in
// the measurement point's tangent plane (the 3D sum of eq. 6.38 is biased even under
// uniform light; digest 4.5). With t = |v_t| / r, v_t the tangent part of
// (photon - point):
//     lap K = -30 t (t-1) (5t-3) / r^2          (K'' + K'/t, over r^2)
// The pass's sums go into the batch's per-pixel sums at the radius r it used (digest 11.2):
//     S += w Phi_K / (k1 r^2 c),  D += M / (pi r^2),  G += lap / (k1 r^2 c),  GR += r^2 G's term
// where M is the raw photon count (the radius rule is count based) and c the share of the
// disc's kernel weight on the point's own surface (eye_pass.cl, disc_coverage). For the variance
// estimate (eq. 6.22), the pass's own luminance estimate minus the bias estimated at the
// start of the batch, x = L_p - B', adds to X1 and its square to X2; the square of the
// pass's own Laplacian estimate adds to L2 (the noise of the bias estimate). The error
// sums exist only when the layout has them (SUM_G defined). K1, the luminance weights and
// the record layout SUM_* come from kernels/contract.py as build options.

inline float luminance(float3 c) { return dot(c, (float3)(LUM_R, LUM_G, LUM_B)); }

#define MIN_COVERAGE 0.05f  /* a disc almost all beyond walls: do not divide by ~0 */
#define NEAR_BATCH 16       /* photons within the radius tested and added at a time (gather_exact) */

typedef struct {
    float3 phi;   // sum of K(t) * flux (rgb)
    float lap;    // sum of lap K * luminance(w * flux)
    float phi_half;  // sum of K(2t) * luminance(w * flux): the same gather at radius r/2
    float m;      // photons counted (raw)
} PassSums;

// A photon at p counts for the query at x (normal n, radius^2 r2) if it lies in the
// disc's ball (photon_near), has arrived on the side the eye sees, and lies on a surface
// that matches the point's (photon_matches; its incoming direction and surface normal,
// unit vectors; NORMAL_MATCH_COS, contract.py). The last test keeps a concave corner
// from gathering the photons of the perpendicular wall, which would brighten it; the disc
// coverage measured in the eye pass then renormalises the estimate for the part of the disc
// beyond that wall, and only photons in that covered part count (inside_cut, eye_pass.cl: no
// light through a wall from the same plane beyond it).
inline bool photon_near(float3 x, float r2, float3 p) {
    float3 v = p - x;
    return dot(v, v) < r2;
}

inline bool photon_matches(float3 n, float3 incoming, float3 normal) {
    return dot(incoming, n) > 0.0f && dot(normal, n) > NORMAL_MATCH_COS;
}

inline void add_photon(PassSums* s, float3 x, float3 n, float r, float3 wgt, float4 pp, float3 flux, float count) {
    float3 v = pp.xyz - x;
    float3 vt = v - dot(v, n) * n;
    float t = fmin(length(vt) / r, 1.0f);
    float k = 1.0f - t * t * t * (10.0f - 15.0f * t + 6.0f * t * t);
    s->phi += k * flux * count;
    s->m += count;
#ifdef SUM_G
    float y = luminance(wgt * flux) * count;
    s->lap += -30.0f * t * (t - 1.0f) * (5.0f * t - 3.0f) / (r * r) * y;
    float t2 = fmin(2.0f * t, 1.0f);
    s->phi_half += (1.0f - t2 * t2 * t2 * (10.0f - 15.0f * t2 + 6.0f * t2 * t2)) * y;
#endif
}

// Add one pass's gather to pixel gid's sums (sums.cl).
#define ADD_SUM(name, value) (*sum_at(batch_sums, n_pixels, gid, name, 1) += (value))

inline void accumulate(__global double* batch_sums, int n_pixels, int gid, float r, float3 wgt,
                       float2 coverage, PassSums s, float photons, float bias) {
    double kr2 = K1 * (double)r * (double)r * (double)coverage.x;  // the kernel weight of the covered disc
    double3 flux = convert_double3(wgt * s.phi) / kr2;
    __global double* rgb = sum_at(batch_sums, n_pixels, gid, SUM_S, 3);
    rgb[0] += flux.x;
    rgb[1] += flux.y;
    rgb[2] += flux.z;
    ADD_SUM(SUM_D, (double)s.m / (M_PI * (double)r * (double)r));
    ADD_SUM(SUM_H, 1.0);
#ifdef SUM_G
    double lap = (double)s.lap / kr2;
    ADD_SUM(SUM_G, lap);
    ADD_SUM(SUM_GR, lap * (double)r * (double)r);  // at the pass's own radius: eq. 6.18's sum
    ADD_SUM(SUM_L2, (lap / (double)photons) * (lap / (double)photons));  // the pass's own lap L, squared
    double x = dot(flux, (double3)(LUM_R, LUM_G, LUM_B)) / (double)photons - (double)bias;
    ADD_SUM(SUM_X1, x);
    ADD_SUM(SUM_X2, x * x);
    // The pass's luminance estimate at r less the one at r/2 (same photons): where the
    // density is smooth this is 3/4 of the bias at r; at an edge it shows the bias directly.
    double dh = x + (double)bias - (double)s.phi_half / (0.25 * K1 * (double)r * (double)r * (double)coverage.y)
                                   / (double)photons;
    ADD_SUM(SUM_DH, dh);
    ADD_SUM(SUM_DH2, dh * dh);
#endif
}

// The radius rule within a batch (worker/stats.py, eqs. 6.5-6.6): after each pass the
// pixel's count and radius move on as a sequential SPPM run's would, N' = N + alpha M and
// R'^2 = R^2 (N + alpha M) / (N + M), so the batch's next pass gathers at the radius it
// would have had, whatever the batch's length. A batch's first pass stands for `steps`
// passes of the job: itself and, before it, the job's passes its inputs lack (other
// batches', rendering or not yet folded; GatherInputs): the rule is taken once per step,
// each with the photons this pass found scaled to that step's disc, M (R_j / R)^2 (the
// others' photons, unseen here, are of the same density in expectation), so the pass
// gathers at the radius of its place in the job's pass order. The bias its per-pass
// samples subtract (0.5 R^2 c lap L) scales with R^2. Returns this pass's own photons at
// its own step `own` (M (R_own / R)^2): N's increment from this pass is alpha times that,
// whenever and in whatever group the batch is merged (sum M).
//
// Past SHRINK_LOOP_STEPS steps (a long catch-up: many workers, or a slow folder) the steps are
// taken in closed form: with C_j = N_j / (R_j / R)^2 the rule reads C_{j+1} = C_j + M and
// N_{j+1} = N_j (x_j + alpha) / x_j, x_j = C_j / M, so N_{j+k} = N_j G(x_j + k) / G(x_j),
// G(x) = Gamma(x + alpha) / Gamma(x), and (R_j / R)^2 = N_j / C_j. Its log comes from
// Stirling's series once x is past SHRINK_SERIES_FROM (the steps before it are looped): a
// few logs in place of a loop whose length grew with the job's workers.
#define SHRINK_LOOP_STEPS 16u
#define SHRINK_SERIES_FROM 8.0

// log(Gamma(x + a) / Gamma(x)), x >= SHRINK_SERIES_FROM: within 1e-6 for a in (0, 1].
inline double log_gamma_ratio(double x, double a) {
    double q = a * (a - 1.0);
    return a * log(x) + q / (2.0 * x) - q * (2.0 * a - 1.0) / (12.0 * x * x) + q * q / (12.0 * x * x * x);
}

inline float shrink_radius(int gid, float m, float alpha, uint steps, uint own, __global float* radius,
                           __global float* radius_count, __global float* bias) {
    if (m <= 0.0f) return 0.0f;
    float n = radius_count[gid], r2 = 1.0f, own_m = m;  // r2: (R_j / R)^2
    if (steps <= SHRINK_LOOP_STEPS) {
        for (uint j = 0; j < steps; ++j) {
            float mj = m * r2;
            if (j == own) own_m = mj;
            r2 *= (n + alpha * mj) / (n + mj);
            n += alpha * mj;
        }
    } else {
        double md = m, al = alpha, nd = n, cd = n, own_d = md;  // C_0 = N_0 (R_0 = R)
        uint j = 0;
        for (; j < steps && cd < SHRINK_SERIES_FROM * md; ++j) {  // the first steps, to the series' range
            double mj = j == 0 ? md : md * nd / cd;
            if (j == own) own_d = mj;
            nd += al * mj;
            cd += md;
        }
        if (j < steps) {  // the rest in closed form
            double x = cd / md, lx = log_gamma_ratio(x, al);
            if (own >= j && own < steps)
                own_d = md * nd * exp(log_gamma_ratio(x + (own - j), al) - lx) / (cd + (own - j) * md);
            nd *= exp(log_gamma_ratio(x + (steps - j), al) - lx);
            cd += (steps - j) * md;
        }
        own_m = (float)own_d;
        n = (float)nd;
        r2 = (float)(nd / cd);
    }
    radius_count[gid] = n;
    radius[gid] *= sqrt(r2);
    bias[gid] *= r2;
    return own_m;
}

// A pixel's query this pass; false if the pixel has no measurement point.
typedef struct {
    float3 x, n, wgt;
    float2 coverage;  // share of the disc's kernel weight on the point's surface, at r and r/2
    uint4 cut;        // where the coverage rays found the disc cut (inside_cut)
    float r, r2;
} Query;

// The distinct table entries of the cells that the box of the ball (x, r) overlaps, r at
// most half a cell (the grids' rule), so at most 2 cells per axis (hi is clamped to lo + 1
// against rounding at exactly r = cell/2). Each entry once: where two of the cells collide
// in the table, its items are visited once and every item within r counts once, with no
// test of which cell it lies in (one in a colliding far cell fails the distance test).
// Used by the stochastic gather, the adaptive sampler's point grid (visibility.cl) and the
// hybrid integrator's merging (vcm_camera_pass.cl); the exact gather reads rows
// (ball_rows). Returns how many entries were written.
inline int ball_entries(float3 x, float r, float inv_cell, uint mask, uint entries[8]) {
    int3 lo = cell_of(x - r, inv_cell);
    int3 hi = min(cell_of(x + r, inv_cell), lo + 1);
    int n = 0;
    for (int cz = lo.z; cz <= hi.z; ++cz)
        for (int cy = lo.y; cy <= hi.y; ++cy)
            for (int cx = lo.x; cx <= hi.x; ++cx) {
                uint h = cell_hash((int3)(cx, cy, cz), mask);
                bool seen = false;
                for (int k = 0; k < n; ++k) seen |= entries[k] == h;
                if (!seen) entries[n++] = h;
            }
    return n;
}

inline bool start_query(int gid, __global const float4* mp_pos, __global const float4* mp_nrm,
                        __global const float4* mp_wgt, __global const uint4* mp_cut, __global const float* radius,
                        Query* q) {
    float4 mp = mp_pos[gid];
    if (mp.w == 0.0f) return false;
    q->x = mp.xyz;
    q->n = mp_nrm[gid].xyz;
    float4 w = mp_wgt[gid];
    q->wgt = w.xyz;
    q->coverage = fmax((float2)(w.w, mp_nrm[gid].w), MIN_COVERAGE);
    q->cut = mp_cut[gid];
    q->r = radius[gid];
    q->r2 = q->r * q->r;
    return true;
}

// The rows of the exact grid's cells (runs of consecutive x) that the box of the ball
// (x, r) overlaps, r at most half a cell (the grids' rule; GRID_ROW_SPLIT cells along x): at
// most 2 rows a side, 4 in all, each a run of consecutive table entries (cell_hash) and so
// one run of the grid's photons, GRID_ROW_SPLIT + 1 cells long at most. Every row has the
// same length.
typedef struct {
    uint first[4];  // each row's first entry
    int n;
    uint len;       // cells in a row
} BallRows;

inline void ball_rows(float3 x, float r, float inv_cell, uint mask, BallRows* rows) {
    int3 lo = split_cell_of(x - r, inv_cell, GRID_ROW_SPLIT);
    int3 hi = min(split_cell_of(x + r, inv_cell, GRID_ROW_SPLIT), lo + (int3)(GRID_ROW_SPLIT, 1, 1));
    rows->len = (uint)(hi.x - lo.x + 1);
    rows->n = 0;
    for (int cz = lo.z; cz <= hi.z; ++cz)
        for (int cy = lo.y; cy <= hi.y; ++cy)
            rows->first[rows->n++] = cell_hash((int3)(lo.x, cy, cz), mask);
}

// Row i's cells that an earlier row's run already covers (two rows' runs overlap in the
// table: rare), as bits: each entry is visited once, as ball_entries does.
inline uint rows_seen(const BallRows* rows, int i, uint mask) {
    uint seen = 0, len = rows->len, all = (1u << len) - 1u;
    for (int k = 0; k < i; ++k) {
        uint ahead = (rows->first[i] - rows->first[k]) & mask;   // row i starts inside row k
        uint behind = (rows->first[k] - rows->first[i]) & mask;  // row k starts inside row i
        if (ahead < len) seen |= all >> ahead;
        if (behind < len) seen |= all & ~((1u << behind) - 1u);
    }
    return seen;
}

__kernel void gather_stochastic(int n_pixels, __global const float4* mp_pos, __global const float4* mp_nrm,
                                __global const float4* mp_wgt, __global const uint4* mp_cut,
                                __global float* radius,
                                __global float* radius_count, __global float* bias, float alpha, uint steps, uint own,
                                float photons,
                                float inv_cell, uint mask, __global const uint* tab_count,
                                __global const float4* tab_pos, __global const float4* tab_flux,
                                __global const uint2* tab_dirs,
                                __global double* batch_sums) {
    int gid = get_global_id(0);
    Query q;
    if (gid >= n_pixels || !start_query(gid, mp_pos, mp_nrm, mp_wgt, mp_cut, radius, &q)) return;
    PassSums s = {(float3)(0.0f), 0.0f, 0.0f, 0.0f};
    uint entries[8];
    int n_entries = ball_entries(q.x, q.r, inv_cell, mask, entries);
    for (int k = 0; k < n_entries; ++k) {
        uint h = entries[k];
        uint count = tab_count[h];
        if (count == 0) continue;
        float4 pp = tab_pos[h];
        uint2 dirs = tab_dirs[h];
        if (photon_near(q.x, q.r2, pp.xyz) && photon_matches(q.n, unpack_dir(dirs.x), unpack_dir(dirs.y))
            && inside_cut(q.cut, q.n, pp.xyz - q.x, q.r))
            add_photon(&s, q.x, q.n, q.r, q.wgt, pp, tab_flux[h].xyz, (float)count * pp.w);  // w: 1, or a chain pass's scale
    }
    accumulate(batch_sums, n_pixels, gid, q.r, q.wgt, q.coverage, s, photons, bias[gid]);
    ADD_SUM(SUM_M, (double)shrink_radius(gid, s.m, alpha, steps, own, radius, radius_count, bias));
}

// Add the photons near[0 .. n) of the exact grid that match the query's surface and lie in
// its disc's covered part.
inline void add_near(PassSums* s, const Query* q, const uint* near, int n, __global const float4* grid_pos,
                     __global const float4* grid_flux, __global const float4* grid_in,
                     __global const float4* grid_nrm) {
    for (int m = 0; m < n; ++m) {
        uint j = near[m];
        if (photon_matches(q->n, grid_in[j].xyz, grid_nrm[j].xyz) && inside_cut(q->cut, q->n, grid_pos[j].xyz - q->x, q->r))
            add_photon(s, q->x, q->n, q->r, q->wgt, grid_pos[j], grid_flux[j].xyz, grid_pos[j].w);  // w: the photon's count
    }
}

// Test the exact grid's photons begin .. end against the query's ball, adding those within
// a batch at a time (add_near). The distance test runs without a branch, collecting the
// photons it keeps to be tested and added NEAR_BATCH at a time: a branch per visited photon
// would mispredict often.
inline void scan_run(PassSums* s, const Query* q, uint begin, uint end, uint* near, int* n_near,
                     __global const float4* grid_pos, __global const float4* grid_flux,
                     __global const float4* grid_in, __global const float4* grid_nrm) {
    for (uint j = begin; j < end; ++j) {
        near[*n_near] = j;
        *n_near += photon_near(q->x, q->r2, grid_pos[j].xyz) ? 1 : 0;
        if (*n_near == NEAR_BATCH) {
            add_near(s, q, near, *n_near, grid_pos, grid_flux, grid_in, grid_nrm);
            *n_near = 0;
        }
    }
}

__kernel void gather_exact(int n_pixels, __global const float4* mp_pos, __global const float4* mp_nrm,
                           __global const float4* mp_wgt, __global const uint4* mp_cut,
                           __global float* radius,
                           __global float* radius_count, __global float* bias, float alpha, uint steps, uint own,
                           float photons,
                           float inv_cell, uint mask, __global const uint* cell_start,
                           __global const uint* cell_count, __global const float4* grid_pos,
                           __global const float4* grid_flux, __global const float4* grid_in,
                           __global const float4* grid_nrm, __global double* batch_sums) {
    int gid = get_global_id(0);
    Query q;
    if (gid >= n_pixels || !start_query(gid, mp_pos, mp_nrm, mp_wgt, mp_cut, radius, &q)) return;
    PassSums s = {(float3)(0.0f), 0.0f, 0.0f, 0.0f};
    BallRows rows;
    ball_rows(q.x, q.r, inv_cell, mask, &rows);
    uint near[NEAR_BATCH];
    int n_near = 0;
    for (int i = 0; i < rows.n; ++i) {
        // The row's entries not seen before: each run of consecutive ones (not wrapping past
        // the table's end) is one run of photons, from its first entry's start to its last's end.
        uint seen = rows_seen(&rows, i, mask), first = rows.first[i];
        for (uint t = 0; t < rows.len;) {
            if (seen >> t & 1u) {
                ++t;
                continue;
            }
            uint u = t + 1;
            while (u < rows.len && !(seen >> u & 1u) && ((first + u) & mask) != 0) ++u;
            uint last = (first + u - 1) & mask;
            scan_run(&s, &q, cell_start[(first + t) & mask], cell_start[last] + cell_count[last], near, &n_near,
                     grid_pos, grid_flux, grid_in, grid_nrm);
            t = u;
        }
    }
    add_near(&s, &q, near, n_near, grid_pos, grid_flux, grid_in, grid_nrm);
    accumulate(batch_sums, n_pixels, gid, q.r, q.wgt, q.coverage, s, photons, bias[gid]);
    ADD_SUM(SUM_M, (double)shrink_radius(gid, s.m, alpha, steps, own, radius, radius_count, bias));
}
