"""Mitsuba's `serialized` mesh format: read (and written, for tests and benchmarks) with zlib and NumPy.

The layout, as Mitsuba's documentation of the `serialized` shape gives it. A file holds one
or more shapes back to back; each is

    uint16 0x041C (format id), uint16 version (3 or 4), then a zlib stream holding:
    uint32 flags (0x0001 vertex normals, 0x0002 texture coordinates, 0x0008 vertex colours,
                  0x0010 face normals wanted, 0x1000 float32 data, 0x2000 float64 data),
    (version 4) the shape's name, UTF-8, NUL-terminated,
    uint64 vertex count, uint64 triangle count,
    positions [3 V], normals [3 V] if flagged, texture coordinates [2 V] if flagged,
    colours [3 V] if flagged (all float32 or float64 as flagged),
    indices [3 T] (uint32, or uint64 when V > 2^32 - 1),

all little-endian. The file ends with a table: each shape's byte offset (uint64 in version
4, uint32 in version 3) and last the number of shapes (uint32).
"""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass

import numpy as np

from worker.meshes import MeshData, MeshError, check_mesh

FORMAT_ID = 0x041C
HAS_NORMALS, HAS_TEXCOORDS, HAS_COLORS, FACE_NORMALS = 0x0001, 0x0002, 0x0008, 0x0010
SINGLE, DOUBLE = 0x1000, 0x2000


@dataclass(frozen=True)
class SerializedShape:
    mesh: MeshData  # normals None when the file has none
    face_normals: bool  # the file asks for flat shading


def shape_count(data: bytes) -> int:
    """How many shapes the file's end table lists."""
    if len(data) < 8:
        raise MeshError("too short for a serialized mesh")
    return struct.unpack_from("<I", data, len(data) - 4)[0]


def _offset(data: bytes, index: int) -> int:
    count = shape_count(data)
    if not 0 <= index < count:
        raise MeshError(f"shape_index {index} is outside 0..{count - 1} (the file holds {count} shapes)")
    version = struct.unpack_from("<H", data, 2)[0]
    size = 8 if version >= 4 else 4
    table = len(data) - 4 - size * count
    if table < 0:
        raise MeshError("the shape table is truncated")
    return struct.unpack_from("<Q" if size == 8 else "<I", data, table + size * index)[0]


def header_counts(data: bytes, index: int) -> tuple[int, int]:
    """(vertices, triangles) of shape `index`, decompressing only the stream's first bytes."""
    raw, _, _ = _stream_start(data, index, 4096)
    return _counts(raw)[1:]


def _stream_start(data: bytes, index: int, size: int | None) -> tuple[bytes, int, int]:
    offset = _offset(data, index)
    if offset + 4 > len(data):
        raise MeshError(f"shape {index} lies past the end of the file")
    ident, version = struct.unpack_from("<HH", data, offset)
    if ident != FORMAT_ID or version not in (3, 4):
        raise MeshError(f"shape {index} is not a serialized mesh (id {ident:#06x}, version {version})")
    stream = zlib.decompressobj()
    try:
        raw = stream.decompress(data[offset + 4:], size or 0) if size else stream.decompress(data[offset + 4:])
    except zlib.error as exc:
        raise MeshError(f"shape {index}: corrupt zlib stream ({exc})") from None
    return raw, version, offset


def _counts(raw: bytes, version: int = 4) -> tuple[int, int, int]:
    """(position after the counts, vertices, triangles) of a decompressed shape stream."""
    if len(raw) < 4:
        raise MeshError("truncated shape header")
    pos = 4
    if version >= 4:
        end = raw.find(b"\0", pos)
        if end < 0:
            raise MeshError("unterminated shape name")
        pos = end + 1
    if len(raw) < pos + 16:
        raise MeshError("truncated shape header")
    vertices, triangles = struct.unpack_from("<QQ", raw, pos)
    return pos + 16, vertices, triangles


def read_serialized(data: bytes, index: int = 0) -> SerializedShape:
    """Shape `index` of a serialized file's bytes; MeshError (one line) if it is not one."""
    raw, version, _ = _stream_start(data, index, None)
    flags = struct.unpack_from("<I", raw, 0)[0]
    pos, nv, nt = _counts(raw, version)
    real = np.float64 if flags & DOUBLE else np.float32
    width = np.dtype(real).itemsize
    need = {"positions": 3, "normals": 3 if flags & HAS_NORMALS else 0,
            "texcoords": 2 if flags & HAS_TEXCOORDS else 0, "colors": 3 if flags & HAS_COLORS else 0}
    index_type = np.uint64 if nv > 0xFFFFFFFF else np.uint32
    total = nv * width * sum(need.values()) + nt * 3 * np.dtype(index_type).itemsize
    if len(raw) - pos < total:
        raise MeshError(f"shape {index} holds fewer bytes than its {nv} vertices and {nt} triangles need")
    arrays: dict[str, np.ndarray | None] = {}
    for name, k in need.items():
        arrays[name] = np.frombuffer(raw, real, nv * k, pos).reshape(-1, k) if name != "colors" and k else None
        pos += nv * k * width
    triangles = np.frombuffer(raw, index_type, nt * 3, pos).reshape(-1, 3)
    positions = arrays["positions"]
    assert positions is not None
    mesh = check_mesh(positions, triangles, arrays["normals"], arrays["texcoords"])
    return SerializedShape(mesh, bool(flags & FACE_NORMALS))


def write_serialized(shapes: list[tuple[np.ndarray, np.ndarray, np.ndarray | None]], name: str = "") -> bytes:
    """A version-4 serialized file (float32) of (vertices, triangles, normals or None) shapes."""
    out, offsets = bytearray(), []
    for vertices, triangles, normals in shapes:
        flags = SINGLE | (HAS_NORMALS if normals is not None else 0)
        body = struct.pack("<I", flags) + name.encode() + b"\0" + struct.pack("<QQ", len(vertices), len(triangles))
        body += np.asarray(vertices, "<f4").tobytes()
        if normals is not None:
            body += np.asarray(normals, "<f4").tobytes()
        body += np.asarray(triangles, "<u4").tobytes()
        offsets.append(len(out))
        out += struct.pack("<HH", FORMAT_ID, 4) + zlib.compress(body, 1)
    out += struct.pack(f"<{len(offsets)}Q", *offsets) + struct.pack("<I", len(offsets))
    return bytes(out)
