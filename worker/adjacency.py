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

A point walks only where its disc may reach such an edge. On its own triangle and its
neighbours the eye pass tests the edges themselves; farther along a mesh (a fine mesh: the
disc spans many triangles) it reads a bound the host computes once per triangle
(`far_edge_bounds`): how near any point of the triangle can come to an edge where its
surface ends, on a triangle beyond its neighbours.
"""

from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components, dijkstra
from scipy.spatial import cKDTree

from kernels.contract import EXTENT_STEPS, NORMAL_MATCH_COS

NO_NEIGHBOUR = -1
# far_edge_bounds looks at this many edge samples nearest a triangle at most (when the
# nearest ones belong to the triangle or its neighbours), and queries this many triangles at
# a time.
NEAREST_SAMPLES = 32
QUERY_CHUNK = 1 << 16


def triangle_neighbours(tris: np.ndarray) -> np.ndarray:
    """(T, 4) int32: columns 0-2 the triangle across edge j (corner j to corner j + 1, corners
    v0, v0 + e1, v0 + e2) on the same surface, or NO_NEIGHBOUR; column 3 the float32 bits of
    `far_edge_bounds`, negative where the triangle or a neighbour has an edge where its
    surface ends (kernels/eye_pass.cl, disc_leaves_surface: it tests such edges near a point
    only there, and walks farther only where the bound lies within the disc's reach)."""
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
    by_position = np.lexsort((bits[:, 2], bits[:, 1], bits[:, 0]))  # (np.unique by rows is far slower)
    new_corner = np.ones(len(by_position), bool)
    new_corner[1:] = (bits[by_position[1:]] != bits[by_position[:-1]]).any(axis=1)
    corner_id: np.ndarray = np.empty(len(by_position), np.int64)
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

    # Triangles that have, or whose neighbours have, an edge where the surface ends: the
    # bound's sign (-0.0 where it is 0).
    across = out[:, :3]
    ends = (across == NO_NEIGHBOUR).any(axis=1)
    near = ends | (ends[np.maximum(across, 0)] & (across != NO_NEIGHBOUR)).any(axis=1)
    far = far_edge_bounds(corners, across)
    out[:, 3] = np.where(near, -far, far).view(np.int32)
    return out


def far_edge_bounds(corners: np.ndarray, across: np.ndarray) -> np.ndarray:
    """(T,) float32: for each triangle a lower bound on the distance from any of its points to
    an edge where its surface ends (no neighbour across it) on another triangle of its
    surface (connected through neighbours) that is not one of its neighbours; inf where the
    eye pass's walk cannot reach one (none, or EXTENT_STEPS triangles away or more: the walk
    moves a triangle a step).

    From samples along those edges, spaced at most h apart (h the median open edge's length
    on the surface): the nearest sample not on the triangle or a neighbour, less h / 2, less
    the triangle's reach from its centroid; where the NEAREST_SAMPLES nearest are all on it or
    its neighbours, the farthest of them. No farther than the walk goes (EXTENT_STEPS
    triangles of the surface's median size, its horizon): a search beyond would visit most
    of the tree, and the bound is then the horizon. All surfaces share one k-d tree, each
    scaled to a horizon of 1 and set 3 apart along a fourth axis, so a search within the
    horizon stays on its own surface."""
    n = len(corners)
    bound = np.full(n, np.inf, np.float32)
    # Surfaces: triangles connected through neighbours. One of 2 triangles has none beyond
    # its neighbours (a quad), so only larger ones are looked at.
    linked, _ = np.nonzero(across != NO_NEIGHBOUR)
    neighbour = across[across != NO_NEIGHBOUR]
    _, surface = connected_components(coo_matrix((np.ones(len(linked), np.int8), (linked, neighbour)), shape=(n, n)),
                                      directed=False)
    large = np.bincount(surface)[surface] > 2
    t, j = np.nonzero((across == NO_NEIGHBOUR) & large[:, None])
    if len(t) == 0:
        return bound
    # Steps from the triangles with such an edge (a source joined to each), as far as the walk goes.
    rows, cols = np.concatenate([linked, np.full(len(t), n)]), np.concatenate([neighbour, t])
    walk = coo_matrix((np.ones(len(rows), np.int8), (rows, cols)), shape=(n + 1, n + 1))
    steps = dijkstra(walk, directed=False, indices=n, unweighted=True, limit=EXTENT_STEPS + 1)[:n] - 1
    tris = np.nonzero(large & (steps < EXTENT_STEPS))[0]
    if len(tris) == 0:
        return bound

    # Each surface's sample spacing h and horizon, from its open edges and its triangles.
    centre = corners[tris].astype(np.float64).mean(axis=1)
    spread = np.linalg.norm(corners[tris] - centre[:, None, :], axis=2).max(axis=1)
    p0 = corners[t, j].astype(np.float64)
    p1 = corners[t, (j + 1) % 3].astype(np.float64)
    length = np.linalg.norm(p1 - p0, axis=1)
    h = _median_by(length, surface[t], len(surface))
    horizon = np.maximum(EXTENT_STEPS * _median_by(spread, surface[tris], len(surface)), 1e-30)

    # The samples, each surface scaled to its horizon and set apart from the others.
    pieces = np.maximum(1, np.ceil(length / np.maximum(h[surface[t]], 1e-30))).astype(np.int64)
    edge = np.repeat(np.arange(len(t)), pieces + 1)
    step = np.arange(len(edge)) - np.repeat(np.cumsum(pieces + 1) - (pieces + 1), pieces + 1)
    f = (step / pieces[edge])[:, None]
    owner = t[edge]
    tree = cKDTree(_scaled(p0[edge] * (1.0 - f) + p1[edge] * f, surface[owner], horizon))

    # Per triangle: the nearest sample beyond itself and its neighbours. The nearest sample
    # of all is that for most triangles; the rest look at more.
    at = _scaled(centre, surface[tris], horizon)
    nearest = np.full(len(tris), np.inf)  # inf: none within the horizon
    todo = np.arange(len(tris))
    widest = min(NEAREST_SAMPLES, len(owner))
    for k in (1, widest):
        left = []
        for lo in range(0, len(todo), QUERY_CHUNK):
            part = todo[lo:lo + QUERY_CHUNK]
            dist, idx = tree.query(at[part], k=k, distance_upper_bound=1.0)
            dist, idx = dist.reshape(len(part), k), idx.reshape(len(part), k)
            seen = idx < len(owner)  # within the horizon
            who = owner[np.where(seen, idx, 0)]
            tri = tris[part]
            counts = seen & (who != tri[:, None]) & (who[:, :, None] != across[tri][:, None, :]).all(axis=2)
            first = counts.argmax(axis=1)
            found = counts[np.arange(len(part)), first]
            nearest[part[found]] = dist[np.arange(len(part)), first][found]
            if k == widest:  # the farthest seen bounds the rest
                nearest[part[~found]] = dist[~found, -1]
            else:  # a wider look where the nearest sample lies within the horizon and does not count
                left.append(part[~found & seen[:, 0]])
        todo = np.concatenate(left) if left else todo[:0]
        if len(todo) == 0:
            break
    reach = horizon[surface[tris]]
    bound[tris] = np.maximum(0.0, (np.minimum(nearest, 1.0) * reach - 0.5 * h[surface[tris]] - spread) * (1.0 - 1e-6))
    return bound


def _median_by(values: np.ndarray, groups: np.ndarray, n_groups: int) -> np.ndarray:
    """(n_groups,) the median of `values` in each group (the upper one of an even count; 0
    for a group with none)."""
    order = np.lexsort((values, groups))
    counts = np.bincount(groups, minlength=n_groups)
    starts = np.cumsum(counts) - counts
    out = np.zeros(n_groups)
    has = counts > 0
    out[has] = values[order][starts[has] + counts[has] // 2]
    return out


def _scaled(points: np.ndarray, surface: np.ndarray, horizon: np.ndarray) -> np.ndarray:
    """Points of each surface in units of its horizon, with the surface 3 horizons apart from
    the next along a fourth axis: (N, 4)."""
    return np.column_stack([points / horizon[surface][:, None], 3.0 * surface])
