"""Triangle meshes from Wavefront OBJ and PLY (ASCII and binary) files, read by trimesh.

Only trimesh's parsers are used (`trimesh.exchange`), not its processing: vertices keep
their order and nothing is merged, so the triangles are exactly the file's. Per-vertex
normals are kept where the file has them for every vertex (smooth shading); otherwise the
mesh is flat. Every failure, whatever the parser raised, is a `MeshError` with one line
of text: a user's file is input, and input never ends in a traceback.
"""

from __future__ import annotations

import io
import logging
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

MESH_SUFFIXES = (".obj", ".ply")

logging.getLogger("trimesh").setLevel(logging.ERROR)  # its debug chatter is not ours to log


class MeshError(ValueError):
    """A mesh file that cannot be read (the caller adds the scene field)."""


@dataclass(frozen=True)
class MeshData:
    vertices: np.ndarray  # (V, 3) float64
    triangles: np.ndarray  # (T, 3) int64, indices into vertices
    normals: np.ndarray | None  # (V, 3) float64 per-vertex shading normals, or None (flat)


def _check_obj_indices(path: Path) -> None:
    """OBJ indices are 1-based (negative: from the end); trimesh reads a 0 as vertex 1."""
    with path.open("rb") as fh:
        for lineno, line in enumerate(fh, 1):
            parts = line.split()
            if parts and parts[0] == b"f" and any(p.split(b"/")[0] in (b"0", b"-0") for p in parts[1:]):
                raise MeshError(f"line {lineno}: face index 0 (OBJ indices start at 1)")


def _parse(path: Path) -> list[dict]:
    """The parser's raw geometry dicts (one per OBJ object; one for a PLY)."""
    from trimesh.exchange import obj, ply

    if path.suffix.lower() == ".obj":
        _check_obj_indices(path)
    with warnings.catch_warnings(), path.open("rb") as fh:
        warnings.simplefilter("ignore")  # numpy warnings from trimesh's texture code
        if path.suffix.lower() == ".ply":
            return [ply.load_ply(fh)]
        # OBJ is ASCII text; bytes that are not UTF-8 (a comment or a name in another
        # encoding) become U+FFFD here, where trimesh would guess an encoding with a package
        # we do not install.
        text = io.StringIO(fh.read().decode("utf-8", errors="replace"))
        return list(obj.load_obj(text, maintain_order=True)["geometry"].values())


def _triangulate(faces: object) -> np.ndarray:
    """Triangles from the parser's faces (PLY may hold quads or mixed polygons)."""
    from trimesh.geometry import triangulate_quads

    f = np.asarray(faces) if not isinstance(faces, list) else faces
    if isinstance(f, np.ndarray) and f.ndim == 2 and f.shape[1] == 3:
        return f.astype(np.int64)
    return np.asarray(triangulate_quads(f), np.int64).reshape(-1, 3)


def check_mesh(vertices: np.ndarray, triangles: np.ndarray, normals: np.ndarray | None) -> MeshData:
    """Shapes, index range and finiteness of a mesh, from a file or given inline."""
    v = np.asarray(vertices, np.float64)
    f = np.asarray(triangles)
    if v.ndim != 2 or v.shape[1] != 3 or len(v) == 0:
        raise MeshError("no vertices")
    if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0 or not np.issubdtype(f.dtype, np.integer):
        raise MeshError("no triangles")
    f = f.astype(np.int64)
    if f.min() < 0 or f.max() >= len(v):
        raise MeshError(f"a triangle indexes a vertex outside 0..{len(v) - 1}")
    if not np.all(np.isfinite(v)):
        raise MeshError("non-finite vertex coordinate")
    n = None
    if normals is not None:
        n = np.asarray(normals, np.float64)
        if n.shape != v.shape:
            raise MeshError(f"{len(n)} normals for {len(v)} vertices")
        if not np.all(np.isfinite(n)):
            raise MeshError("non-finite normal")
    return MeshData(v, f, n)


def load_mesh(path: Path) -> MeshData:
    """Read an .obj or .ply file; MeshError with a one-line reason if it is not a mesh."""
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise MeshError(f"unsupported mesh format {path.suffix!r} (have: .obj, .ply)")
    try:
        parts = _parse(path)
    except MeshError:
        raise
    except Exception as exc:  # noqa: BLE001 - any parser failure is a malformed file
        raise MeshError(f"malformed {path.suffix.lower()[1:].upper()}: {exc}") from None
    parts = [p for p in parts if len(p.get("faces", ())) > 0]
    if not parts:
        raise MeshError("the file holds no triangles")

    # Concatenate the objects, offsetting each one's indices past the vertices before it.
    offsets = np.cumsum([0] + [len(p["vertices"]) for p in parts[:-1]])
    vertices = np.concatenate([np.asarray(p["vertices"], np.float64).reshape(-1, 3) for p in parts])
    triangles = np.concatenate([_triangulate(p["faces"]) + o for p, o in zip(parts, offsets, strict=True)])
    have_normals = all(p.get("vertex_normals") is not None for p in parts)
    normals = np.concatenate([np.asarray(p["vertex_normals"], np.float64) for p in parts]) if have_normals else None
    return check_mesh(vertices, triangles, normals)
