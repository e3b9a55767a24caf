"""Triangle adjacency for the gather disc's convex edges (kernels/eye_pass.cl, surface_extent).

A measurement point's disc lies on its own surface. Where that surface ends in empty space
(a convex edge: a table top's rim, a box's front edge, a quad's outer edge) the disc hangs
over nothing, no photon lies there, and an estimate that divides by the whole disc is dark
by the share it hangs over (half at the edge). The eye pass finds where the surface ends by
walking from triangle to triangle in each coverage ray's direction; this module gives the
walk its map: for each triangle edge, the triangle across it on the same surface.

Two triangles continue one surface across an edge when they share both its corners (the
same float32 positions: a quad's two halves, a mesh's indexed neighbours) and their normals,
taken with the winding the shared edge implies, lie within the gather's normal match
(NORMAL_MATCH_COS). Anything else ends the surface there: an edge of one triangle alone, a
fold beyond 45 degrees, an edge shared by three or more. A surface split where it does not
end (coplanar quads that share no corners) only cuts the disc at a line with photons on
both sides; the estimate counts the disc's covered part and its photons alike, so it loses
photons there, not its expectation.
"""

from __future__ import annotations

import numpy as np

from kernels.contract import NORMAL_MATCH_COS

NO_NEIGHBOUR = -1


def triangle_neighbours(tris: np.ndarray) -> np.ndarray:
    """(T, 4) int32: columns 0-2 the triangle across edge j (corner j to corner j + 1, corners
    v0, v0 + e1, v0 + e2) on the same surface, or NO_NEIGHBOUR; column 3 is 1 where the
    triangle or a neighbour has an edge where its surface ends (the eye pass looks for such
    an edge near a point only there: kernels/eye_pass.cl, disc_leaves_surface)."""
    n = len(tris)
    out = np.full((n, 4), NO_NEIGHBOUR, np.int32)
    if n == 0:
        return out
    corners = np.ascontiguousarray(tris, np.float32)
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]).astype(np.float64)
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-300)

    # Corners by position (the same float32 bits: the same corner), then each edge once per
    # triangle: (triangle, edge j, its corners' ids), keyed by the sorted pair of ids.
    bits = (corners.reshape(-1, 3) + np.float32(0.0)).view(np.uint32)  # -0.0 and 0.0: one corner
    by_position = np.lexsort((bits[:, 2], bits[:, 1], bits[:, 0]))  # (np.unique by rows: 14x slower)
    new_corner = np.ones(len(by_position), bool)
    new_corner[1:] = (bits[by_position[1:]] != bits[by_position[:-1]]).any(axis=1)
    corner_id = np.empty(len(by_position), np.int64)
    corner_id[by_position] = np.cumsum(new_corner) - 1
    corner_id = corner_id.reshape(n, 3)
    tri = np.repeat(np.arange(n), 3)
    edge = np.tile(np.arange(3), n)
    a, b = corner_id[tri, edge], corner_id[tri, (edge + 1) % 3]
    forward = a < b  # the edge's direction against its sorted corners: the winding
    key = np.minimum(a, b) * (3 * n) + np.maximum(a, b)
    _, group, counts = np.unique(key, return_inverse=True, return_counts=True)

    # Edges shared by exactly two triangles: neighbours if their normals match.
    shared = counts[group] == 2
    order = np.argsort(group, kind="stable")
    order = order[shared[order]]
    first, second = order[0::2], order[1::2]
    t1, t2 = tri[first], tri[second]
    # Opposite windings along the edge (the consistent case) compare the normals as they are;
    # the same winding means one triangle is turned over.
    sign = np.where(forward[first] != forward[second], 1.0, -1.0)
    match = sign * np.einsum("ij,ij->i", normals[t1], normals[t2]) > NORMAL_MATCH_COS
    match &= t1 != t2
    out[t1[match], edge[first][match]] = t2[match]
    out[t2[match], edge[second][match]] = t1[match]

    # Triangles that have, or whose neighbours have, an edge where the surface ends.
    across = out[:, :3]
    ends = (across == NO_NEIGHBOUR).any(axis=1)
    out[:, 3] = ends | (ends[np.maximum(across, 0)] & (across != NO_NEIGHBOUR)).any(axis=1)
    return out
