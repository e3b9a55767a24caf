// The light vertices in grid order, for merging (vcm_camera_pass.cl, merge_light_vertices).
// spatial_hash.cl's counting sort leaves `sorted`, the vertex slots grouped by table entry
// (each entry's slots sorted by vertex key); this copies each slot's position next to it,
// pos.w = the slot, so a query reads an entry's candidates from one contiguous run and
// loads a whole vertex only for those within the radius.
__kernel void vcm_grid_positions(uint n, __global const uint* sorted, __global const float4* lv_pos,
                                 __global float4* grid_pos) {
    uint j = get_global_id(0);
    if (j >= n) return;
    uint i = sorted[j];
    grid_pos[j] = (float4)(lv_pos[i].xyz, as_float(i));
}

// The table entries of the 8 cells a query at x of radius r <= cell / 2 overlaps (the
// rule of spatial_hash.cl), each entry once: where two of the cells collide in the table,
// its vertices are visited once and every vertex within r is counted once, with no test of
// which cell it lies in (one that lies in a colliding cell farther away fails the distance
// test). Returns how many distinct entries were written to `entries`.
inline int query_entries(float3 x, float inv_cell, uint mask, uint entries[8]) {
    QueryCells q = query_cells(x, inv_cell);
    int n = 0;
    for (int k = 0; k < 8; ++k) {
        uint h = cell_hash(query_cell(q, k), mask);
        bool seen = false;
        for (int m = 0; m < n; ++m) seen |= entries[m] == h;
        if (!seen) entries[n++] = h;
    }
    return n;
}
