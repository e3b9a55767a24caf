"""The image and error estimate a job's folder publishes after each round, for any API
process to serve (the API holds no job state).

    pf:job:{id}:image   hash   passes, emitted, counters (JSON), rgb: (pixels, 3) float32;
                               with an estimate also average, confidence, and per pixel
                               luminance, bias, noise, bound, relative (float32), measured,
                               known (uint8)

Written with REPL_NONE, outside the append-only file and any replica, as a batch's delta
is (worker/store/state.py): it is 33 bytes a pixel, a third of a GB a round at 3840x2160,
and the folded state it is made from is durable. An image a restart lost is made again from
the tiles by whoever reads it (Jobs.published). An image with fewer passes than the one
held is not written (a worker's stale fold racing the reducer's round).
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass, fields

import numpy as np
import redis

from worker.error_estimate import ErrorEstimate
from worker.integrators import Integrator
from worker.integrators.base import State
from worker.store import keys
from worker.store.connection import binary, text

# KEYS: the job record, its image. ARGV: the passes, then the image's fields and values.
# The image takes the record's retention time if the record has one (a job ended meanwhile).
PUBLISH = """
local held = redis.call('HGET', KEYS[2], 'passes')
if held and tonumber(held) > tonumber(ARGV[1]) then return 0 end
redis.set_repl(redis.REPL_NONE)
redis.call('DEL', KEYS[2])
redis.call('HSET', KEYS[2], unpack(ARGV, 2))
local ttl = redis.call('PTTL', KEYS[1])
if ttl > 0 then redis.call('PEXPIRE', KEYS[2], ttl) end
return 1
"""
PIXEL_LAYERS = ("luminance", "bias", "noise", "bound", "relative")  # float32 per pixel
MASKS = ("measured", "known")  # uint8 per pixel


@dataclass(frozen=True)
class Published:
    """A job's image as its last fold round left it: what the API serves."""

    passes: int
    emitted: int
    counters: dict[str, int]
    rgb: np.ndarray  # (pixels, 3) float32
    estimate: ErrorEstimate | None  # None where the job estimates no error

    @classmethod
    def of(cls, integrator: Integrator, state: State, estimate: ErrorEstimate | None = None) -> Published:
        """The image of `state`; `estimate` if the caller has it (a fold round made it), else computed."""
        if estimate is None and state.passes > 0:
            estimate = integrator.estimate(state)
        return cls(state.passes, state.emitted, dict(state.counters),
                   np.ascontiguousarray(integrator.image(state), np.float32), estimate)

    def encode(self) -> dict[str, bytes | str | int | float]:
        out: dict[str, bytes | str | int | float] = {
            "passes": self.passes, "emitted": self.emitted, "counters": json.dumps(self.counters),
            "rgb": self.rgb.tobytes()}
        if self.estimate is not None:
            out |= {"average": repr(self.estimate.average), "confidence": repr(self.estimate.confidence)}
            out |= {name: np.ascontiguousarray(getattr(self.estimate, name), np.float32).tobytes()
                    for name in PIXEL_LAYERS}
            out |= {name: np.ascontiguousarray(getattr(self.estimate, name), np.uint8).tobytes() for name in MASKS}
        return out

    @classmethod
    def decode(cls, h: Mapping[bytes, bytes] | Mapping[bytes | str, bytes | str]) -> Published:
        f = {text(k): v for k, v in h.items()}

        def array(name: str, dtype: type) -> np.ndarray:
            return np.frombuffer(binary(f[name]), dtype)

        estimate = None
        if "average" in f:
            per_pixel = {name: array(name, np.float32) for name in PIXEL_LAYERS} | \
                        {name: array(name, np.uint8).astype(bool) for name in MASKS}
            estimate = ErrorEstimate(**per_pixel, average=float(text(f["average"])),
                                     confidence=float(text(f["confidence"])))
        return cls(int(text(f["passes"])), int(text(f["emitted"])), json.loads(text(f["counters"])),
                   array("rgb", np.float32).reshape(-1, 3), estimate)


assert {f.name for f in fields(ErrorEstimate)} == {*PIXEL_LAYERS, *MASKS, "average", "confidence"}


class Images:
    """Publishing and reading jobs' images on the main Redis."""

    def __init__(self, conn: redis.Redis) -> None:
        self.r = conn
        self._publish = conn.register_script(PUBLISH)

    def publish(self, job_id: str, image: Published) -> bool:
        """Publish the job's image; False if the one held has more passes."""
        flat = [v for item in image.encode().items() for v in item]
        return bool(self._publish(keys=[keys.job(job_id), keys.image(job_id)], args=[image.passes, *flat]))

    def get(self, job_id: str) -> Published | None:
        h = self.r.hgetall(keys.image(job_id))
        return Published.decode(h) if h else None
