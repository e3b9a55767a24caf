"""The job state cut into pixel tiles, each on one of the state's Redis nodes, and the
encodings of what moves per tile: the folded state, a batch's delta and a batch's inputs.

A tile is a run of TILE_PIXELS consecutive pixels (row-major, so a band of rows at most
frame sizes: 65,536 pixels, 8.4 MB of state at 128 bytes a pixel); tile k lives on node k mod (number of nodes). The nodes are the Redis URLs
in PHOTONFARM_STATE_URLS (comma-separated), else the main Redis alone; a job records how
many nodes it was created with, and every process must name the same nodes in the same
order. Queues, job records and leases always stay on the main Redis.

Encodings (all little-endian numpy bytes, no pickle: nothing read from Redis runs code):
- state: every array of the integrator's `state_widths`, float64, in that order.
- delta: a JSON header naming the arrays sent (a tile's all-zero arrays are left out),
  a newline, then those arrays as float64.
- inputs: a JSON header naming the per-pixel fields of the integrator's batch inputs and
  holding its other fields (numbers, or dataclasses of numbers, e.g. the adaptive sampler's
  chain inputs, exactly as computed), a newline, then the per-pixel fields as float32
  (what the kernels read).
"""

from __future__ import annotations

import dataclasses
import json
import os
import threading
import typing
from collections import OrderedDict
from dataclasses import dataclass
from typing import Any

import numpy as np
import redis

from worker.store.connection import connect

# Pixels a tile holds (a job keeps the size it was created with; tests make tiles small).
TILE_PIXELS = int(os.environ.get("PHOTONFARM_TILE_PIXELS", str(1 << 16)))
STATE_URLS_ENV = "PHOTONFARM_STATE_URLS"
# Folded tiles a process keeps (the API process reads what it folded without a round trip;
# 2 GB holds a 3840 x 2160 job's state).
CACHE_BYTES = int(float(os.environ.get("PHOTONFARM_TILE_CACHE_MB", "2048")) * 1e6)


def state_nodes(main: redis.Redis) -> list[redis.Redis]:
    """The Redis nodes that hold job states: PHOTONFARM_STATE_URLS, else the main Redis."""
    urls = [u.strip() for u in os.environ.get(STATE_URLS_ENV, "").split(",") if u.strip()]
    return [connect(u) for u in urls] or [main]


@dataclass(frozen=True)
class Tiling:
    """Which pixels each tile holds and which node holds each tile."""

    n_pixels: int
    n_nodes: int
    tile_pixels: int = TILE_PIXELS

    @property
    def count(self) -> int:
        return max(1, -(-self.n_pixels // self.tile_pixels))

    def span(self, k: int) -> slice:
        return slice(k * self.tile_pixels, min(self.n_pixels, (k + 1) * self.tile_pixels))

    def node(self, k: int) -> int:
        return k % self.n_nodes

    def by_node(self) -> dict[int, list[int]]:
        out: dict[int, list[int]] = {}
        for k in range(self.count):
            out.setdefault(self.node(k), []).append(k)
        return out


# ------------------------------------------------------------------- the state
def encode_state(arrays: dict[str, np.ndarray], widths: dict[str, int], span: slice) -> bytes:
    return b"".join(np.ascontiguousarray(arrays[name][span], np.float64).tobytes() for name in widths)


def decode_state(blob: bytes, widths: dict[str, int], n: int) -> dict[str, np.ndarray]:
    flat = np.frombuffer(blob, np.float64)
    out, at = {}, 0
    for name, width in widths.items():
        part = flat[at:at + n * width]
        out[name] = part.reshape(n, width) if width > 1 else part
        at += n * width
    return out


# ------------------------------------------------------------------- a delta
def encode_delta(sums: dict[str, np.ndarray], span: slice) -> bytes:
    """One tile's part of a batch's sums; arrays that are zero over the tile are left out."""
    parts = {name: np.ascontiguousarray(a[span], np.float64) for name, a in sums.items()}
    sent = [name for name, a in parts.items() if a.any()]
    return json.dumps(sent).encode() + b"\n" + b"".join(parts[name].tobytes() for name in sent)


def decode_delta(payload: bytes, widths: dict[str, int], n: int) -> dict[str, np.ndarray]:
    """The arrays a tile's delta carries (the rest are zero)."""
    header, _, body = payload.partition(b"\n")
    sent = json.loads(header)
    return decode_state(body, {name: widths[name] for name in sent}, n)


# ------------------------------------------------------------------ the inputs
def encode_inputs(inputs: Any, span: slice) -> bytes:
    """One tile's part of a batch's inputs (a dataclass, or None): per-pixel arrays cut to
    the tile, every other field whole in the header."""
    if inputs is None:
        return b"null\n"
    present = {f.name: getattr(inputs, f.name) for f in dataclasses.fields(inputs)}
    sent = [name for name, a in present.items() if isinstance(a, np.ndarray)]
    scalars = {name: dataclasses.asdict(v) if dataclasses.is_dataclass(v) else v
               for name, v in present.items() if name not in sent}
    return json.dumps({"arrays": sent, "scalars": scalars}).encode() + b"\n" + b"".join(
        np.ascontiguousarray(present[name][span], np.float32).tobytes() for name in sent)


def _field_value(kind: type, name: str, value: Any) -> Any:
    """A header field back as the inputs type declares it: a dict becomes the dataclass the
    field's annotation names (`X | None` included)."""
    if not isinstance(value, dict):
        return value
    hint = typing.get_type_hints(kind)[name]
    target = next(t for t in (hint, *typing.get_args(hint)) if dataclasses.is_dataclass(t))
    return target(**value)


def decode_inputs(blobs: list[bytes], spans: list[slice], n_pixels: int, kind: type | None) -> Any:
    """The whole frame's batch inputs from its tiles' parts."""
    header = json.loads(blobs[0].partition(b"\n")[0])
    if header is None:
        return None
    fields: dict[str, Any] = {name: np.empty(n_pixels, np.float32) for name in header["arrays"]}
    for blob, span in zip(blobs, spans):
        body = np.frombuffer(blob.partition(b"\n")[2], np.float32)
        n = span.stop - span.start
        for i, name in enumerate(header["arrays"]):
            fields[name][span] = body[i * n:(i + 1) * n]
    fields.update({name: _field_value(kind, name, v) for name, v in header["scalars"].items()})
    return kind(**fields)


class TileCache:
    """Folded tiles by (job, tile) with the version they were read or written at, bounded
    in bytes: a tile whose node still shows that version need not be read again."""

    def __init__(self, max_bytes: int = CACHE_BYTES) -> None:
        self.max_bytes = max_bytes
        self._items: OrderedDict[tuple[str, int], tuple[int, bytes]] = OrderedDict()
        self._bytes = 0
        self._lock = threading.Lock()

    def get(self, job_id: str, k: int, version: int) -> bytes | None:
        with self._lock:
            item = self._items.get((job_id, k))
            if item is None or item[0] != version:
                return None
            self._items.move_to_end((job_id, k))
            return item[1]

    def put(self, job_id: str, k: int, version: int, blob: bytes) -> None:
        with self._lock:
            old = self._items.pop((job_id, k), None)
            self._bytes -= len(old[1]) if old else 0
            if len(blob) > self.max_bytes:
                return
            self._items[(job_id, k)] = (version, blob)
            self._bytes += len(blob)
            while self._bytes > self.max_bytes:
                _, (_, dropped) = self._items.popitem(last=False)
                self._bytes -= len(dropped)


CACHE = TileCache()
