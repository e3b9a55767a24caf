"""BVH structure: every triangle in exactly one leaf, boxes enclose what they hold."""

from __future__ import annotations

import numpy as np

from worker.bvh import LEAF_SIZE, build_bvh


def _walk(lo: np.ndarray, hi: np.ndarray, node: int, out: list[tuple[int, int, int]]) -> None:
    a, b = int(lo[node, 3].view(np.int32)), int(hi[node, 3].view(np.int32))
    if b > 0:
        out.append((node, a, b))
        return
    _walk(lo, hi, node + 1, out)
    _walk(lo, hi, a, out)


def test_bvh_partitions_triangles_into_enclosing_leaves() -> None:
    rng = np.random.default_rng(1)
    centres = rng.uniform(-50, 50, (1000, 1, 3))
    tris = centres + rng.normal(0, 1.0, (1000, 3, 3))
    lo, hi, order = build_bvh(tris)
    assert sorted(order.tolist()) == list(range(1000))
    leaves: list[tuple[int, int, int]] = []
    _walk(lo, hi, 0, leaves)
    covered = sorted(i for _, first, count in leaves for i in range(first, first + count))
    assert covered == list(range(1000))
    reordered = tris[order]
    for node, first, count in leaves:
        assert 1 <= count <= LEAF_SIZE
        t = reordered[first:first + count].reshape(-1, 3)
        assert np.all(t >= lo[node, :3]) and np.all(t <= hi[node, :3])
    # Every interior box encloses its children's boxes.
    for node in range(len(lo)):
        if int(hi[node, 3].view(np.int32)) == 0:
            for child in (node + 1, int(lo[node, 3].view(np.int32))):
                assert np.all(lo[child, :3] >= lo[node, :3]) and np.all(hi[child, :3] <= hi[node, :3])
