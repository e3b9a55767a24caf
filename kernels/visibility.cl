// Photon path visibility V(u) (adaptive photon tracing, Hachisuka & Jensen 2011, sec. 3.2):
// a photon counts as visible when it lands where some measurement point of the current
// pass would gather it. The photon grid of spatial_hash.cl indexes photons; this is the
// reverse lookup, a grid over the pass's measurement points (built with the same
// grid_count / grid_scan / grid_scatter kernels, cell = 2 * largest radius), queried at a
// photon's position over the cells a disc of radius <= cell/2 can reach (ball_entries).
//
// The tests are the gather's (photon_near, photon_matches, inside_cut): inside the point's disc
// and its covered part, arrived on the side the eye sees, on a surface matching the point's.
// Each is taken with a hair of slack
// (VIS_SLACK) so that V is a superset of what the gather counts: a path V calls invisible
// must never deposit into a point, or the chains (which only ever keep visible paths)
// would miss its light; the reverse only costs a little efficiency.

#define VIS_SLACK 1e-5f

typedef struct {
    __global const float4* mp_pos;   // w: 1 if the pixel has a point this pass
    __global const float4* mp_nrm;
    __global const uint4* mp_cut;    // the disc's covered part (inside_cut, eye_pass.cl)
    __global const float* radius;
    __global const uint* cell_start;
    __global const uint* cell_count;
    __global const uint* sorted;     // point indices, by grid entry
    float inv_cell;
    uint mask;
} PointGrid;

// Whether the photon at pp (packed incoming direction and normal `dirs`) lands in the
// gather disc of some measurement point.
inline bool photon_visible(const PointGrid* grid, float3 pp, uint2 dirs) {
    float3 in_dir = unpack_dir(dirs.x), nrm = unpack_dir(dirs.y);
    uint entries[8];
    int n_entries = ball_entries(pp, 0.5f / grid->inv_cell, grid->inv_cell, grid->mask, entries);
    for (int k = 0; k < n_entries; ++k) {
        uint begin = grid->cell_start[entries[k]], end = begin + grid->cell_count[entries[k]];
        for (uint j = begin; j < end; ++j) {
            uint i = grid->sorted[j];
            float4 mp = grid->mp_pos[i];
            if (mp.w == 0.0f) continue;
            float r = grid->radius[i];
            float3 v = pp - mp.xyz, n = grid->mp_nrm[i].xyz;
            if (dot(v, v) >= r * r * (1.0f + VIS_SLACK)) continue;
            if (dot(in_dir, n) <= -VIS_SLACK) continue;
            if (dot(nrm, n) > NORMAL_MATCH_COS - VIS_SLACK &&
                inside_cut(grid->mp_cut[i], n, v, r * (1.0f + VIS_SLACK))) return true;
        }
    }
    return false;
}
