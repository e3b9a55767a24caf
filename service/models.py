"""Request and response bodies of the HTTP API, with the service's documented limits."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from worker.engine import RenderSettings
from worker.scene import MAX_SCENE_NAME, SCENE_NAME_PATTERN, bundled_scene_names

# Service limits (README, "Limits"): each answers 413 or 422 naming what it limits.
MAX_BODY_BYTES = 16 * 1024 * 1024
MAX_SERVICE_PIXELS = 1280 * 1024  # per job; the job state is 64 bytes per pixel in Redis
MAX_SERVICE_PHOTONS_PER_PASS = 1 << 22
MAX_ACTIVE_JOBS = 16
DEFAULT_MAX_SECONDS = 300.0  # when a job names no budget at all


class JobSettings(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    method: Literal["sppm", "ppm"] = "sppm"
    gather: Literal["stochastic", "exact"] = RenderSettings.gather
    alpha: float = Field(0.7, gt=0.0, le=1.0)
    photons_per_pass: int = Field(RenderSettings.photons_per_pass, ge=1, le=MAX_SERVICE_PHOTONS_PER_PASS)
    max_passes: int | None = Field(None, ge=1, le=10_000_000)
    max_seconds: float | None = Field(None, gt=0.0, le=7 * 86_400.0)
    seed: int = Field(0, ge=0, lt=2 ** 63)
    resolution: tuple[int, int] | None = None
    priority: Literal["high", "normal", "low"] = "normal"
    initial_radius: float | None = Field(None, gt=0.0)
    error_threshold: float | None = Field(None, gt=0.0, le=10.0,
                                          description="stop, as converged, when the average relative error is at most this")
    confidence: float = Field(0.9, gt=0.0, lt=1.0, description="of the per-pixel error bound; 0.5 bounds the median error (README)")
    bias_constant: Literal["taylor", "dissertation"] = "taylor"

    @model_validator(mode="after")
    def _budget(self) -> "JobSettings":
        if self.resolution is not None and (min(self.resolution) < 1 or self.resolution[0] * self.resolution[1] > MAX_SERVICE_PIXELS):
            raise ValueError(f"resolution must have positive sides and at most {MAX_SERVICE_PIXELS} pixels")
        if self.max_passes is None and self.max_seconds is None:  # also with a threshold: it may be out of reach
            self.max_seconds = DEFAULT_MAX_SECONDS
        return self


class JobRequest(BaseModel):
    model_config = ConfigDict(extra="forbid")

    scene: dict[str, Any] | None = Field(None, description="a scene in the format of scenes/*.json")
    scene_name: str | None = Field(None, description="a bundled scene, see GET /v1/scenes",
                                   pattern=SCENE_NAME_PATTERN, max_length=MAX_SCENE_NAME)
    settings: JobSettings = Field(default_factory=JobSettings)

    @field_validator("scene_name")
    @classmethod
    def _bundled(cls, name: str | None) -> str | None:
        if name is not None and name not in (names := bundled_scene_names()):
            raise ValueError(f"no bundled scene {name!r} (have: {', '.join(names)})")
        return name

    @model_validator(mode="after")
    def _one_scene(self) -> "JobRequest":
        if (self.scene is None) == (self.scene_name is None):
            raise ValueError("give exactly one of scene and scene_name")
        return self


class JobLinks(BaseModel):
    self: str
    image_png: str
    image_exr: str
    error_png: str
    error_exr: str


class ErrorPoint(BaseModel):
    passes: int
    photons: int
    seconds: float
    error: float = Field(description="estimated average relative error at the job's confidence")


class JobView(BaseModel):
    id: str
    status: Literal["queued", "running", "cancel-requested", "cancelled", "converged", "completed", "failed"]
    scene_name: str | None
    settings: dict[str, Any]
    width: int
    height: int
    passes: int = Field(description="passes merged into the estimate")
    photons: int = Field(description="photon paths emitted by the merged passes")
    elapsed_seconds: float
    photons_per_second: float
    workers_active: int
    created: str
    started: str | None
    finished: str | None
    failure: str | None = Field(description="why the job failed")
    error_estimate: ErrorPoint | None = Field(description="the latest estimate (after the last merge)")
    error_history: list[ErrorPoint] | None = Field(None, description="every estimate so far (single-job view)")
    links: JobLinks


class SceneSummary(BaseModel):
    name: str
    description: str


class ErrorBody(BaseModel):
    """Every 4xx answer: a message, or (422) a list of {loc, msg, type} naming each bad field."""

    detail: str | list[dict[str, Any]]
