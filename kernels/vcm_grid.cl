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
