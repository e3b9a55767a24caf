"""Bounding volume hierarchy over triangles, built on the host with numpy.

Layout read by kernels/geometry.cl: nodes in depth-first pre-order, so an interior
node's left child is the next node. Each node is two float4: (lo.xyz, a) and
(hi.xyz, b) with a, b int32 bit patterns: a leaf has b = primitive count > 0 and
a = first primitive; an interior node has b = 0 and a = index of its right child.
Triangles are reordered so that every leaf's primitives are contiguous.
"""

from __future__ import annotations

import sys

import numpy as np

LEAF_SIZE = 4


def build_bvh(tris: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return (node_lo, node_hi, order): two (n, 4) float32 arrays and the triangle order.

    Splits at the median centroid along the widest axis of the centroid bounds: cheap
    to build, and good enough for the few thousand triangles the bundled scenes hold.
    """
    n = len(tris)
    if n == 0:
        return np.zeros((0, 4), np.float32), np.zeros((0, 4), np.float32), np.zeros(0, np.int64)
    tri_lo = tris.min(axis=1)
    tri_hi = tris.max(axis=1)
    centroid = tris.mean(axis=1)
    order = np.arange(n)
    lo_list: list[np.ndarray] = []
    hi_list: list[np.ndarray] = []
    a_list: list[int] = []
    b_list: list[int] = []

    def build(begin: int, end: int) -> int:
        node = len(lo_list)
        idx = order[begin:end]
        lo_list.append(tri_lo[idx].min(axis=0))
        hi_list.append(tri_hi[idx].max(axis=0))
        a_list.append(begin)
        b_list.append(end - begin)
        if end - begin <= LEAF_SIZE:
            return node
        c = centroid[idx]
        axis = int(np.argmax(c.max(axis=0) - c.min(axis=0)))
        mid = (end - begin) // 2
        order[begin:end] = idx[np.argpartition(c[:, axis], mid)]
        b_list[node] = 0
        build(begin, begin + mid)
        a_list[node] = build(begin + mid, end)
        return node

    limit = sys.getrecursionlimit()
    sys.setrecursionlimit(max(limit, 10_000))
    try:
        build(0, n)
    finally:
        sys.setrecursionlimit(limit)

    # Round boxes outward so float32 boxes still contain the float64 triangles.
    lo = np.nextafter(np.array(lo_list, np.float32), np.float32(-np.inf))
    hi = np.nextafter(np.array(hi_list, np.float32), np.float32(np.inf))
    node_lo = np.empty((len(lo), 4), np.float32)
    node_hi = np.empty((len(hi), 4), np.float32)
    node_lo[:, :3] = lo
    node_hi[:, :3] = hi
    node_lo[:, 3] = np.array(a_list, np.int32).view(np.float32)
    node_hi[:, 3] = np.array(b_list, np.int32).view(np.float32)
    return node_lo, node_hi, order
