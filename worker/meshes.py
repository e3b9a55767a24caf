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
import re
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
    uvs: np.ndarray | None = None  # (V, 2) float64 per-vertex texture coordinates, or None


_OBJ_FACE = re.compile(rb"^[ \t]*f[ \t][^\n]*", re.MULTILINE)
_OBJ_VERTEX = re.compile(rb"^[ \t]*v[ \t]", re.MULTILINE)
# A face line with a vertex index (a word's part before any "/") of 0 or -0.
_OBJ_ZERO_INDEX = re.compile(rb"^[ \t]*f[ \t][^\n]*?(?<=[ \t])-?0(?=[/ \t\r\n]|$)", re.MULTILINE)
_PLY_ELEMENT = re.compile(rb"^element[ \t]+(vertex|face)[ \t]+(\d{1,18})[ \t]*\r?$", re.MULTILINE)


def declared_counts(suffix: str, data: bytes) -> tuple[int, int]:
    """(vertices, triangles) a mesh file declares, found without parsing it: an OBJ's `v`
    and `f` lines (each face at least one triangle), a PLY header's element counts."""
    if suffix.lower() == ".obj":
        return len(_OBJ_VERTEX.findall(data)), len(_OBJ_FACE.findall(data))
    header = data[: data.find(b"end_header")] if b"end_header" in data else data[:4096]
    counts = {kind.decode(): int(n) for kind, n in _PLY_ELEMENT.findall(header)}
    return counts.get("vertex", 0), counts.get("face", 0)


def _check_obj_indices(data: bytes) -> None:
    """OBJ indices are 1-based (negative: from the end); trimesh reads a 0 as vertex 1."""
    match = _OBJ_ZERO_INDEX.search(data)
    if match:
        lineno = data.count(b"\n", 0, match.start()) + 1
        raise MeshError(f"line {lineno}: face index 0 (OBJ indices start at 1)")


def _parse(suffix: str, data: bytes) -> list[dict]:
    """The parser's raw geometry dicts (one per OBJ object; one for a PLY)."""
    from trimesh.exchange import obj, ply

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # numpy warnings from trimesh's texture code
        if suffix == ".ply":
            return [ply.load_ply(io.BytesIO(data))]
        _check_obj_indices(data)
        # OBJ is ASCII text; bytes that are not UTF-8 (a comment or a name in another
        # encoding) become U+FFFD here, where trimesh would guess an encoding with a package
        # we do not install.
        text = io.StringIO(data.decode("utf-8", errors="replace"))
        return list(obj.load_obj(text, maintain_order=True)["geometry"].values())


def _triangulate(faces: object) -> np.ndarray:
    """Triangles from the parser's faces (PLY may hold quads or mixed polygons)."""
    from trimesh.geometry import triangulate_quads

    f = np.asarray(faces) if not isinstance(faces, list) else faces
    if isinstance(f, np.ndarray) and f.ndim == 2 and f.shape[1] == 3:
        return f.astype(np.int64)
    return np.asarray(triangulate_quads(f), np.int64).reshape(-1, 3)


def check_mesh(vertices: np.ndarray, triangles: np.ndarray, normals: np.ndarray | None,
               uvs: np.ndarray | None = None) -> MeshData:
    """Shapes, index range and finiteness of a mesh, from a file or given inline."""
    v = np.asarray(vertices, np.float64)
    f = np.asarray(triangles)
    if v.ndim != 2 or v.shape[1] != 3 or len(v) == 0:
        raise MeshError("no vertices")
    if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0 or not np.issubdtype(f.dtype, np.integer):
        raise MeshError("no triangles")
    f = f.astype(np.int64, copy=False)
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
    t = None
    if uvs is not None:
        t = np.asarray(uvs, np.float64)
        if t.shape != (len(v), 2):
            raise MeshError(f"{len(t)} texture coordinates for {len(v)} vertices")
        if not np.all(np.isfinite(t)):
            raise MeshError("non-finite texture coordinate")
    return MeshData(v, f, n, t)


def _uvs(part: dict, flip: bool) -> np.ndarray | None:
    """A parsed part's per-vertex texture coordinates, or None if it has none for every vertex."""
    uv = getattr(part.get("visual"), "uv", None)
    if uv is None or len(uv) != len(part["vertices"]):
        return None
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    return np.column_stack([uv[:, 0], 1.0 - uv[:, 1]]) if flip else uv


def load_mesh(path: Path, data: bytes | None = None) -> MeshData:
    """Read an .obj or .ply file (`data`: its bytes, if already read); MeshError with a
    one-line reason if it is not a mesh."""
    suffix = path.suffix.lower()
    if suffix not in MESH_SUFFIXES:
        raise MeshError(f"unsupported mesh format {path.suffix!r} (have: .obj, .ply)")
    try:
        parts = _parse(suffix, path.read_bytes() if data is None else data)
    except MeshError:
        raise
    except Exception as exc:  # any parser failure is a malformed file
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
    uvs = [_uvs(p, flip=suffix == ".obj") for p in parts]
    every = [u for u in uvs if u is not None]
    return check_mesh(vertices, triangles, normals, np.concatenate(every) if len(every) == len(parts) else None)
