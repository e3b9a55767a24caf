"""Request and response bodies of the HTTP API, with the service's documented limits."""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from worker.scene import MAX_RESOLUTION, MAX_SCENE_NAME, SCENE_NAME_PATTERN, bundled_scene_names
from worker.settings import Settings
from worker.store.policy import Status
from worker.store.record import MAX_JOB_NOTES, MAX_NOTE_CHARS

# Service limits (docs/limits.md): each answers 413 or 422 naming what it limits.
MAX_BODY_BYTES = 16 * 1024 * 1024
MAX_SERVICE_PIXELS = 3840 * 2160  # per job
MAX_SERVICE_PHOTONS_PER_PASS = 1 << 22
MAX_ACTIVE_JOBS = 16


def _settings_schema(schema: dict[str, Any]) -> None:
    """The rules the validators check beyond each field's type, said in the JSON schema so
    that it admits what the API accepts: each side of the resolution, the sampler that
    needs a photon method, the threshold that needs the error estimate. (The pixels of a
    job, a product of its sides, are checked but not said: JSON Schema has no product.)"""
    resolution = schema["properties"]["resolution"]["anyOf"][0]
    for side in resolution["prefixItems"]:
        side.update(minimum=1, maximum=MAX_RESOLUTION)
    schema["allOf"] = [
        {"if": {"properties": {"sampler": {"const": "adaptive"}}, "required": ["sampler"]},
         "then": {"properties": {"method": {"enum": ["sppm", "ppm"]}}}},
        {"if": {"properties": {"error_threshold": {"type": "number"}}, "required": ["error_threshold"]},
         "then": {"properties": {"error_estimation": {"const": True}}}},
    ]


class JobSettings(Settings):
    """The settings model (worker/settings.py) with the service's tighter limits; the
    defaults are the model's own."""

    model_config = ConfigDict(json_schema_extra=_settings_schema)

    photons_per_pass: int | None = Field(None, strict=True, ge=1, le=MAX_SERVICE_PHOTONS_PER_PASS,
                                         description=Settings.model_fields["photons_per_pass"].description)

    @field_validator("resolution")
    @classmethod
    def _service_pixels(cls, value: tuple[int, int] | None) -> tuple[int, int] | None:
        if value is not None and value[0] * value[1] > MAX_SERVICE_PIXELS:
            raise ValueError(f"at most {MAX_SERVICE_PIXELS} pixels per job")
        return value


class JobRequest(BaseModel):
    # Exactly one of scene and scene_name (the validator below), in the schema too.
    model_config = ConfigDict(extra="forbid", json_schema_extra={"oneOf": [
        {"required": ["scene"], "properties": {"scene": {"type": "object"}}},
        {"required": ["scene_name"], "properties": {"scene_name": {"type": "string"}}}]})

    scene: dict[str, Any] | None = Field(None, description="a scene in the format of scenes/*.json")
    scene_name: str | None = Field(None, description="a bundled scene, see GET /v1/scenes",
                                   pattern=SCENE_NAME_PATTERN, max_length=MAX_SCENE_NAME,
                                   json_schema_extra={"enum": [*bundled_scene_names(), None]})
    settings: JobSettings = Field(default_factory=JobSettings)

    @field_validator("scene_name")
    @classmethod
    def _bundled(cls, name: str | None) -> str | None:
        if name is not None and name not in (names := bundled_scene_names()):
            raise ValueError(f"no bundled scene {name!r} (have: {', '.join(names)})")
        return name

    @model_validator(mode="after")
    def _one_scene(self) -> JobRequest:
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
    error: float | None = Field(description="estimated average relative error at the job's confidence "
                                            "(none without error estimation)")


class JobView(BaseModel):
    id: str
    status: Status
    scene_name: str | None
    settings: Settings
    width: int
    height: int
    passes: int = Field(description="passes merged into the job (accepted: they count toward its budget)")
    image_passes: int = Field(description="passes in the current image and error map (folded); at most `passes`, "
                                          "and equal to it once the job is final")
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
    notes: list[str] = Field(description="what the scene holds that was accepted but ignored (\"ignored: "
                                         "...\"), one line each, kept with the job: repeats dropped, each cut "
                                         f"to {MAX_NOTE_CHARS} characters, at most {MAX_JOB_NOTES} and then "
                                         "\"... and N more\"; then what the method decided from the merged "
                                         "passes (\"sampler auto: ...\": measuring, or its choice and the "
                                         "figures it chose by)")
    links: JobLinks


class PixelView(BaseModel):
    """One pixel of a job's current estimate (the viewer's readout under the cursor)."""

    x: int
    y: int = Field(description="row from the top, as in the images")
    passes: int = Field(description="passes merged into the values below")
    rgb: tuple[float, float, float] = Field(description="linear radiance, as in the EXR")
    luminance: float | None = Field(description="the luminance the error is relative to (none without "
                                                "error estimation)")
    bound: float | None = Field(description="error bound at the job's confidence, absolute (luminance)")
    relative_error: float | None = Field(description="bound / max(luminance, floor); 1 where unknown, as in the "
                                                     "error map")
    measured: bool | None = Field(description="the pixel had a measurement point (its error counts in the average)")
    confidence: float | None


class SceneSummary(BaseModel):
    name: str
    description: str


class ErrorBody(BaseModel):
    """Every 4xx answer: a message, or (422) a list of {loc, msg, type} naming each bad field."""

    detail: str | list[dict[str, Any]]
