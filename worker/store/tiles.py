"""The job state cut into pixel tiles, each on one of the state's Redis nodes, and the
encodings of what moves per tile: the folded state, a batch's delta and a batch's inputs.

A tile is a run of `tile_pixels` (worker/config.py) consecutive pixels (row-major, so a
band of rows at most; 65,536 pixels by default, 8.9 MB of state at 136 bytes a pixel);
tile k lives on node k mod (number of nodes). The nodes are the Redis URLs in PHOTONFARM_STATE_URLS
(comma-separated), else the main Redis alone; a job records how many nodes it was created
with, and every process must name the same nodes in the same order. Queues, job records
and leases always stay on the main Redis.

Encodings (all little-endian numpy bytes, no pickle: nothing read from Redis runs code):
- state: a hash, one field per array of the integrator's `state_widths`, float64. A field
  is written only when its array changed (a fold writes the arrays its deltas carried, and
  what the merge derives from them, e.g. N; never the setup arrays again, e.g. R0), and an
  array a tile never received is absent (zero): a tile holds only its setup arrays until
  its first fold, and directly seen emission only where it is seen.
- delta: a JSON header naming the arrays sent (a tile's all-zero arrays are left out) and
  each one's dtype, a newline, then those arrays: float32 (DELTA_DTYPE), or float16
  (HALF_DTYPE) for the sums the integrator's layout names `half`, each such array scaled
  by a power of two that the header gives (its largest value over the tile into
  [2^14, 2^15)). A folder refuses a delta of a dtype it does not read, or naming arrays it
  does not know (DeltaFormatError: a worker of another version), rather than misread it.
- inputs: a JSON header naming the per-pixel fields of the integrator's batch inputs and
  holding its other fields (numbers, or dataclasses of numbers, e.g. the adaptive sampler's
  chain inputs, exactly as computed), a newline, then the per-pixel fields as float32
  (what the kernels read).
A header is padded with spaces to a multiple of 8 bytes, so the arrays after it are read
in place (aligned, no copy); an encoding is written once into one buffer (a state field is
sent straight from the folder's array, no copy).

Why a delta may be float32 or float16 while the state stays float64: a batch's sums are
rounded when sent, to nearest (float16: to float32, then to float16), so each folded sum
is off by at most the unit roundoff (2^-24 = 6e-8 in float32, 2^-11 + 2^-23 = 4.9e-4 in
float16) of the sum of its batches' magnitudes, however many batches are folded (no drift:
the folder adds them in float64), and the same batch always sends the same bytes. What
would drift is float32 *storage* of the running sums, whose error grows with the number of
additions (tests/test_state_precision.py shows both). float16's 4.9e-4 is far below a
batch's own Monte Carlo noise in an image or a radius; it is not below the difference of
the error estimator's moments (the variance X2 - X1^2 / i of per-pass samples that vary by
a few percent cancels to 1e-3 of X2), so those sums, and any mean a variance subtracts, go
as float32 (SumLayout.half names the rest; they are non-negative: a tile's array with a
negative value goes as float32). A float16 array is scaled by a power of two (exact) so
that its largest value over the tile sits just below float16's largest power of two, 2^15:
no sum overflows, and a value down to 2^-28 of that largest keeps float16's 11 bits (below
it, float16's subnormals: off by at most 2^-39 (1 + 2^-13) of the largest). An SPPM delta
with error estimation takes 42 bytes a pixel rather than 60; without, 18 rather than 36.
Fewer bytes go over the network, through the state node (in, out, and through its
checkpoints, which keep the pending deltas within half the state's bytes) and through the
folder.
"""

from __future__ import annotations

import dataclasses
import json
import math
import threading
import typing
from collections import OrderedDict
from collections.abc import Collection
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
import redis

from worker.config import config
from worker.store.connection import Fields, connect, text


def state_nodes(main: redis.Redis) -> list[redis.Redis]:
    """The Redis nodes that hold job states: the configuration's state_urls, else the main Redis."""
    return [connect(u) for u in config().state_urls] or [main]


@dataclass(frozen=True)
class Tiling:
    """Which pixels each tile holds and which node holds each tile."""

    n_pixels: int
    n_nodes: int
    tile_pixels: int

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


DELTA_DTYPE = np.dtype("<f4")  # a batch's sums as sent (the module docstring says why) ...
HALF_DTYPE = np.dtype("<f2")  # ... but those a layout names `half`, ...
HALF_TOP = 15  # ... scaled by 2^e so that their largest magnitude over the tile is below 2^HALF_TOP
HALF_RANGE = 900  # (a largest magnitude beyond 2^+-HALF_RANGE goes as float32: e stays well within float64's range)
HALF_EXPONENTS = range(HALF_TOP - HALF_RANGE, HALF_TOP + HALF_RANGE)  # the e a delta may hold (float32: 0)
DELTA_DTYPES = {dtype.str: dtype for dtype in (DELTA_DTYPE, HALF_DTYPE)}
STATE_DTYPE = np.dtype("<f8")
INPUTS_DTYPE = np.dtype("<f4")  # what the kernels read


class Part(NamedTuple):
    """An array as an encoding holds it: in `dtype` (a float16 part: the array times 2^`exponent`)."""

    array: np.ndarray
    dtype: np.dtype
    exponent: int = 0


def _pack(header: Any, parts: list[Part]) -> memoryview:
    """A JSON header (none if `header` is ...), padded to 8 bytes, then `parts`, each
    converted straight into one buffer (redis-py sends a memoryview as it is)."""
    head = b"" if header is ... else json.dumps(header).encode()
    head = head + b" " * (-(len(head) + 1) % 8) + b"\n" if head else b""
    buf = bytearray(len(head) + sum(p.dtype.itemsize * p.array.size for p in parts))
    buf[:len(head)] = head
    at = len(head)
    for a, dtype, exponent in parts:
        view = np.frombuffer(buf, dtype, a.size, at)
        if dtype == HALF_DTYPE:
            _round_half(a, exponent, view.view(np.uint16))
        else:
            view.reshape(a.shape)[...] = a
        at += dtype.itemsize * a.size
    return memoryview(buf)


def _round_half(a: np.ndarray, exponent: int, out: np.ndarray) -> None:
    """`out` (float16's bits, flat) = `a` times 2^`exponent` (non-negative, below
    2^HALF_TOP), rounded to nearest even twice: to float32, scaled by a further 2^-112 so
    that float16's exponents, subnormals included, are float32's less 112, then to float16
    by dropping 13 mantissa bits (a carry moves into the exponent). Integer steps, since
    numpy's own float16 cast has no vector path on every CPU."""
    x = np.multiply(a, math.ldexp(1.0, exponent - 112), dtype=np.float32).reshape(-1)  # exact but for the rounding
    u = x.view(np.uint32)
    bits = u >> 13
    bits &= 1  # the kept part's lowest bit: a tie rounds to even
    bits += u
    bits += 0xFFF
    bits >>= 13
    out[...] = bits


def _unpack(blob: bytes, dtype: np.dtype) -> tuple[Any, np.ndarray]:
    """A header-led encoding (as read from Redis): its header, and its body read in place."""
    end = blob.index(b"\n")
    return json.loads(blob[:end]), np.frombuffer(blob, dtype, offset=end + 1)


# ------------------------------------------------------------------- the state
def encode_state(arrays: dict[str, np.ndarray], names: list[str], span: slice) -> Fields:
    """A tile's fields of the named state arrays: views of the arrays' bytes (sent as they
    are; the arrays must not change until sent)."""
    return {name: np.ascontiguousarray(arrays[name][span], STATE_DTYPE).reshape(-1).data.cast("B")
            for name in names}


def _buffer(name: object, value: object) -> bytes | memoryview:
    """A state field's value: bytes as Redis replies them, or the view encode_state made."""
    if not isinstance(value, bytes | memoryview):
        raise TypeError(f"state field {name!r} holds {type(value).__name__}, not bytes")
    return value


def decode_state(fields: Fields, widths: dict[str, int], n: int) -> dict[str, np.ndarray]:
    """The arrays a tile's state holds (the rest are zero), read in place. `fields` are as
    encode_state wrote them or as Redis replied (names in bytes)."""
    out = {}
    for key, blob in fields.items():
        name = text(key)
        flat = np.frombuffer(_buffer(name, blob), STATE_DTYPE)
        out[name] = flat.reshape(n, widths[name]) if widths[name] > 1 else flat
    return out


# ------------------------------------------------------------------- a delta
class DeltaFormatError(ValueError):
    """A delta this process cannot read: another dtype, or arrays it does not know (pushed
    by a worker of another version)."""


def _half_part(a: np.ndarray) -> Part | None:
    """A tile's array to go as float16, scaled by the power of two that puts its largest
    value below 2^HALF_TOP (float32 if it holds a negative value or its largest is not
    finite or beyond 2^+-HALF_RANGE; None if the array is zero)."""
    peak = float(a.max())
    if peak == 0.0 and not a.any():
        return None
    if float(a.min()) >= 0.0 and 2.0 ** -HALF_RANGE < peak < 2.0 ** HALF_RANGE:
        return Part(a, HALF_DTYPE, HALF_TOP - math.frexp(peak)[1])
    return Part(a, DELTA_DTYPE)


def encode_delta(sums: dict[str, np.ndarray], span: slice, half: Collection[str] = ()) -> memoryview:
    """One tile's part of a batch's sums; arrays that are zero over the tile are left out,
    those named in `half` go as float16 (the module docstring says why), float32 first
    (aligned)."""
    parts: dict[str, Part] = {}
    for name, a in sums.items():
        part = _half_part(a[span]) if name in half else Part(a[span], DELTA_DTYPE) if a[span].any() else None
        if part is not None:
            parts[name] = part
    sent = sorted(parts, key=lambda name: parts[name].dtype == HALF_DTYPE)
    return _pack({"arrays": sent, "dtypes": [parts[name].dtype.str for name in sent],
                  "exponents": [parts[name].exponent for name in sent]}, [parts[name] for name in sent])


def delta_arrays(payload: bytes) -> list[tuple[str, np.dtype, int]]:
    """The arrays a tile's delta carries, their dtypes and scales (its header), checked to
    be readable here. The version before float16 named one dtype for every array (float32):
    read as such."""
    header = json.loads(payload[:payload.index(b"\n")])
    header = header if isinstance(header, dict) else {}
    arrays = header.get("arrays") or []
    if header.get("dtype") == DELTA_DTYPE.str:
        header = {**header, "dtypes": [DELTA_DTYPE.str] * len(arrays), "exponents": [0] * len(arrays)}
    dtypes = header.get("dtypes")
    unread = [header.get("dtype")] if dtypes is None else sorted(set(dtypes) - set(DELTA_DTYPES))
    if unread or dtypes is None:  # (no dtypes: unread names the header's dtype)
        raise DeltaFormatError(f"its delta is {'in dtype ' + repr(unread[0]) if unread[0] else 'of no named dtype'}, "
                               f"this version reads {' and '.join(map(repr, DELTA_DTYPES))} "
                               f"(a worker of another photonfarm version?)")
    exponents = header.get("exponents")
    if not (isinstance(exponents, list) and len(exponents) == len(arrays) == len(dtypes)
            and all(isinstance(e, int) and e in HALF_EXPONENTS for e in exponents)):
        raise DeltaFormatError("its delta's header does not give a scale for each array it names "
                               "(a worker of another photonfarm version?)")
    return [(name, DELTA_DTYPES[d], e) for name, d, e in zip(arrays, dtypes, exponents, strict=True)]


def decode_delta(payload: bytes, widths: dict[str, int], n: int) -> dict[str, np.ndarray]:
    """The arrays a tile's delta carries (the rest are zero): float32 views, and float16
    arrays scaled back (float64, a tile's worth)."""
    sent = delta_arrays(payload)
    unknown = [name for name, _, _ in sent if name not in widths]
    at, size = payload.index(b"\n") + 1, len(payload)
    if unknown or size - at != sum(n * widths[name] * dtype.itemsize for name, dtype, _ in sent):
        raise DeltaFormatError(f"its delta holds {', '.join(unknown) if unknown else str(size - at) + ' bytes'}, "
                               f"which this version's state does not (a worker of another photonfarm version?)")
    out = {}
    for name, dtype, exponent in sent:
        width = widths[name]
        part = np.frombuffer(payload, dtype, n * width, at)
        if dtype == HALF_DTYPE:  # _round_half backwards: the float32 it rounded, less its 13 dropped bits
            bits = part.view(np.uint16).astype(np.uint32)
            bits <<= 13
            part = np.multiply(bits.view(np.float32), math.ldexp(1.0, 112 - exponent), dtype=np.float64)
        out[name] = part.reshape(n, width) if width > 1 else part
        at += dtype.itemsize * n * width
    return out


def as_sent(sums: dict[str, np.ndarray], tiling: Tiling, half: Collection[str] = ()) -> dict[str, np.ndarray]:
    """A batch's sums as a folder adds them (each tile's delta encoded and read back): the
    folded state is exactly the float64 sum of these."""
    out = {name: np.zeros(a.shape) for name, a in sums.items()}
    widths = {name: a.shape[1] if a.ndim > 1 else 1 for name, a in sums.items()}
    for k in range(tiling.count):
        span = tiling.span(k)
        for name, part in decode_delta(bytes(encode_delta(sums, span, half)), widths, span.stop - span.start).items():
            out[name][span] = part
    return out


# ------------------------------------------------------------------ the inputs
def encode_inputs(inputs: Any, span: slice) -> memoryview:
    """One tile's part of a batch's inputs (a dataclass, or None): per-pixel arrays cut to
    the tile, every other field whole in the header."""
    if inputs is None:
        return _pack(None, [])
    present = {f.name: getattr(inputs, f.name) for f in dataclasses.fields(inputs)}
    sent = [name for name, a in present.items() if isinstance(a, np.ndarray)]
    scalars = {name: dataclasses.asdict(v) if dataclasses.is_dataclass(v) and not isinstance(v, type) else v
               for name, v in present.items() if name not in sent}
    return _pack({"arrays": sent, "scalars": scalars}, [Part(present[name][span], INPUTS_DTYPE) for name in sent])


def _field_value(kind: type, name: str, value: Any) -> Any:
    """A header field back as the inputs type declares it: a dict becomes the dataclass the
    field's annotation names (`X | None` included)."""
    if not isinstance(value, dict):
        return value
    hint = typing.get_type_hints(kind)[name]
    target = next(t for t in (hint, *typing.get_args(hint)) if isinstance(t, type) and dataclasses.is_dataclass(t))
    return target(**value)


class TornInputs(ValueError):
    """Tiles' inputs of different fold rounds: read while a round wrote them (or after a
    folder was killed mid-write, until the next round)."""


def decode_inputs(blobs: list[bytes], spans: list[slice], n_pixels: int, kind: type | None,
                  whole: bool = True) -> Any:
    """The whole frame's batch inputs from its tiles' parts; TornInputs if `whole` and the
    tiles' scalars differ (a round writes the same in every tile: e.g. the passes their
    state holds, from which a batch's radius rule takes its catch-up), else tile 0's."""
    header = _unpack(blobs[0], INPUTS_DTYPE)[0]
    if header is None:
        return None
    fields: dict[str, Any] = {name: np.empty(n_pixels, np.float32) for name in header["arrays"]}
    for blob, span in zip(blobs, spans, strict=True):
        own, body = _unpack(blob, INPUTS_DTYPE)
        if whole and own != header:
            raise TornInputs(f"tile inputs of passes {header['scalars'].get('passes')} and "
                             f"{own['scalars'].get('passes') if own else None}")
        n = span.stop - span.start
        for i, name in enumerate(header["arrays"]):
            fields[name][span] = body[i * n:(i + 1) * n]
    assert kind is not None, "inputs are written only for an integrator that declares their type"
    fields.update({name: _field_value(kind, name, v) for name, v in header["scalars"].items()})
    return kind(**fields)


class TileCache:
    """Folded tiles' state fields by (job, tile) with the version they were read or written
    at, bounded in bytes: a tile whose node still shows that version need not be read again.
    A folder's entries are views of the state arrays of an overlay it dropped (no copy; no
    round changes them: TiledState.checkpoint), so those arrays stay alive while an entry
    refers to them."""

    def __init__(self, max_bytes: int | None = None) -> None:
        self._max_bytes = max_bytes  # None: the configuration's tile cache (Config.tile_cache_bytes)
        self._items: OrderedDict[tuple[str, int], tuple[int, Fields, int]] = OrderedDict()
        self._bytes = 0
        self._lock = threading.Lock()

    @property
    def max_bytes(self) -> int:
        return config().tile_cache_bytes if self._max_bytes is None else self._max_bytes

    def get(self, job_id: str, k: int, version: int) -> Fields | None:
        with self._lock:
            item = self._items.get((job_id, k))
            if item is None or item[0] != version:
                return None
            self._items.move_to_end((job_id, k))
            return item[1]

    def put(self, job_id: str, k: int, version: int, fields: Fields) -> None:
        """A tile's state fields (name -> bytes) at `version`."""
        size = sum(len(memoryview(_buffer(name, v)).cast("B")) for name, v in fields.items())
        with self._lock:
            old = self._items.pop((job_id, k), None)
            self._bytes -= old[2] if old else 0
            if size > self.max_bytes:
                return
            self._items[(job_id, k)] = (version, fields, size)
            self._bytes += size
            while self._bytes > self.max_bytes:
                _, (_, _, dropped) = self._items.popitem(last=False)
                self._bytes -= dropped


CACHE = TileCache()
