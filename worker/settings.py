"""Every render and job setting with its default and its bounds, in one place.

One typed model: the CLI takes its flags' defaults and help from it, the API validates a
job with it, the job store keeps it and gives it back as this model, and the engine takes
it whole. Importable without OpenCL (the API process never renders). The service's own,
tighter limits (pixels and photons per job) are checked in service/models.py.
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, StrictInt, ValidationInfo, field_validator, model_validator

from kernels.contract import MAX_BOUNCES
from worker.scene import MAX_COORD, MAX_PIXELS, MAX_RESOLUTION

MAX_PHOTONS_PER_PASS = 1 << 24
# Paths per pass when none is given (Settings.for_frame): one per pixel, at most
# MAX_DEFAULT_SUBPATHS, in every method. vcm pairs light and camera subpaths one to one
# (Georgiev et al. 2012); photon mapping then balances its photon pass against its eye pass,
# and many short passes shrink its radius and antialias its pixels sooner than a few long ones.
MAX_DEFAULT_SUBPATHS = 1 << 22
DEFAULT_MAX_SECONDS = 300.0  # the budget of a job that names none (a threshold may be out of reach)

Method = Literal["sppm", "ppm", "vcm", "bpt", "lt"]
Gather = Literal["exact", "stochastic"]
Direct = Literal["photons", "nee"]
Sampler = Literal["auto", "uniform", "adaptive"]
Priority = Literal["high", "normal", "low"]
PRIORITIES: tuple[Priority, ...] = ("high", "normal", "low")
# The default radius exponent alpha by method. SPPM's and PPM's 0.7 (the radius rule); the
# hybrid methods' merging radius wants alpha < 2/3 (dissertation ch. 9: the bias then vanishes
# from the MIS weights). bpt and lt do not merge; they share vcm's value so that switching
# merging on or off changes nothing else.
DEFAULT_ALPHA: dict[str, float] = {"sppm": 0.7, "ppm": 0.7, "vcm": 0.6, "bpt": 0.6, "lt": 0.6}


class Settings(BaseModel):
    # Numbers and flags are strict: a string or a boolean where one belongs is refused, not coerced.
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, frozen=True)

    # What is rendered, and how.
    method: Method = Field(default="sppm", description="sppm: new measurement points every pass (stochastic PPM); "
                                               "ppm: one fixed set of points; vcm: vertex connection and "
                                               "merging (bidirectional paths and photon merging, MIS-weighted); "
                                               "bpt: its connections only (unbiased); lt: light tracing")
    gather: Gather = Field(default="exact", description="photon lookup: exact grid, or stochastic spatial hashing "
                                                "(one photon per cell, dissertation ch. 10)")
    direct: Direct = Field(default="photons", description="direct light at the measurement points: photons (density "
                                                  "estimate), or nee (a light sample and a BSDF sample per pass, "
                                                  "MIS-weighted; photons then skip their first hit)")
    sampler: Sampler = Field(default="auto", description="photon paths: uniform; adaptive (Markov chains over "
                                                  "paths that reach a measurement point, replica exchange with "
                                                  "uniform draws; Hachisuka & Jensen 2011); or auto: the job's "
                                                  "first passes time both on the scene and it keeps the one that "
                                                  "brings more new visible paths a second (sppm and ppm; the "
                                                  "other methods trace no photon paths to choose for)")
    target_acceptance: float = Field(default=0.234, strict=True, gt=0.0, lt=1.0,
                                     description="adaptive sampler: the mutation acceptance its mutation size "
                                                 "is adapted toward")
    alpha: float | None = Field(default=None, strict=True, gt=0.0, le=1.0,
                                description="fraction of photons kept per pass (radius rule); vcm: merging radius "
                                "r_k^2 = R0^2 (k+1)^(alpha-1) (default by method: "
                                + ", ".join(f"{m} {a:g}" for m, a in DEFAULT_ALPHA.items()) + ")",
                                json_schema_extra={"x-default-by": {"method": {**DEFAULT_ALPHA}}})
    photons_per_pass: int | None = Field(default=None, strict=True, ge=1, le=MAX_PHOTONS_PER_PASS,
                                         description="photon paths per pass (light subpaths for vcm, bpt, lt); "
                                                     f"default: the pixel count (at most {MAX_DEFAULT_SUBPATHS})")
    initial_radius: float | None = Field(default=None, strict=True, ge=1e-7, le=MAX_COORD,
                                         description="initial gather radius in world units (default: the larger "
                                                     "of 2 pixel footprints and the radius holding 16 photons per "
                                                     "pass at the median lit pixel)")
    hash_entries_per_photon: float = Field(default=1.0, strict=True, gt=0.0, le=64.0,
                                           description="stochastic hash table entries per stored photon")
    seed: int = Field(default=0, strict=True, ge=0, lt=2 ** 63,
                      description="random seed: the same seed gives the same image")
    max_bounces: int = Field(default=MAX_BOUNCES, strict=True, ge=1, le=MAX_BOUNCES,
                             description="safety cap on bounces per path (paths end by Russian roulette; "
                                         "lower it only to study what the cap cuts)")
    resolution: tuple[StrictInt, StrictInt] | None = Field(None, description="[width, height] (default: the scene's)")
    # The error estimate.
    error_estimation: bool = Field(default=True, strict=True,
                                   description="accumulate the error estimator's per-pixel sums")
    confidence: float = Field(default=0.9, strict=True, gt=0.0, lt=1.0,
                              description="of the per-pixel error bound; 0.5 bounds the median error")
    bias_constant: Literal["taylor", "dissertation"] = Field(default="taylor", description="constant c of the bias "
                                                             "estimate 0.5 R^2 c lap L")
    # The job's budget and place in the queues.
    max_passes: int | None = Field(default=None, strict=True, ge=1, le=10_000_000,
                                   description="stop after this many passes")
    max_seconds: float | None = Field(default=None, strict=True, gt=0.0, le=7 * 86_400.0,
                                      description="stop after this many seconds")
    error_threshold: float | None = Field(default=None, strict=True, gt=0.0, le=10.0,
                                          description="stop, as converged, when the average relative error is "
                                                      "at most this")
    priority: Priority = Field(default="normal", description="queue: high, normal or low")

    @field_validator("resolution")
    @classmethod
    def _resolution(cls, value: tuple[int, int] | None) -> tuple[int, int] | None:
        if value is not None:
            w, h = value
            if not (1 <= w <= MAX_RESOLUTION and 1 <= h <= MAX_RESOLUTION):
                raise ValueError(f"each side must lie in 1..{MAX_RESOLUTION}")
            if w * h > MAX_PIXELS:
                raise ValueError(f"at most {MAX_PIXELS} pixels")
        return value

    @field_validator("sampler")
    @classmethod
    def _sampler_needs_photons(cls, value: Sampler, info: ValidationInfo) -> Sampler:
        if value == "adaptive" and info.data.get("method") not in ("sppm", "ppm"):
            raise ValueError("the adaptive sampler traces photons: it applies to methods sppm and ppm")
        return value

    @model_validator(mode="before")
    @classmethod
    def _alpha_by_method(cls, data: Any) -> Any:
        """No alpha given: the method's (DEFAULT_ALPHA), so a settings object always holds
        the alpha it renders with, and a stored job keeps it."""
        if isinstance(data, dict) and data.get("alpha") is None:
            method = data.get("method", cls.model_fields["method"].default)
            if isinstance(method, str) and method in DEFAULT_ALPHA:
                return {**data, "alpha": DEFAULT_ALPHA[method]}
        return data

    @model_validator(mode="before")
    @classmethod
    def _budget(cls, data: Any) -> Any:
        if isinstance(data, dict) and data.get("max_passes") is None and data.get("max_seconds") is None:
            return {**data, "max_seconds": DEFAULT_MAX_SECONDS}
        return data

    @model_validator(mode="after")
    def _threshold_needs_estimate(self) -> Settings:
        if self.error_threshold is not None and not self.error_estimation:
            raise ValueError("error_threshold needs error_estimation")
        return self

    def for_frame(self, width: int, height: int) -> Settings:
        """These settings for a frame of width x height pixels, every frame-dependent default
        filled in (the resolution, the paths per pass), so that a stored job keeps what it
        renders with."""
        paths = self.photons_per_pass if self.photons_per_pass is not None else min(width * height,
                                                                                      MAX_DEFAULT_SUBPATHS)
        return self.model_copy(update={"resolution": self.resolution or (width, height), "photons_per_pass": paths})

    @property
    def paths_per_pass(self) -> int:
        """Paths traced per pass; the settings must have been through `for_frame`."""
        if self.photons_per_pass is None:
            raise ValueError("settings not yet given a frame (Settings.for_frame)")
        return self.photons_per_pass


DEFAULTS = Settings()
