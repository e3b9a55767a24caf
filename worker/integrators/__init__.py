"""Rendering methods by name. The host halves are importable without OpenCL; the device
halves are imported where rendering happens (worker/engine.py)."""

from __future__ import annotations

from worker.integrators.base import Delta, Integrator
from worker.integrators.connect_merge import BidirectionalPathTracing, ConnectMerge, LightTracing
from worker.integrators.photon_mapping import PhotonMapping, ProgressivePhotonMapping
from worker.settings import Settings

INTEGRATORS: dict[str, type[Integrator]] = {
    cls.name: cls for cls in (PhotonMapping, ProgressivePhotonMapping, ConnectMerge, BidirectionalPathTracing,
                              LightTracing)}


def integrator_for(settings: Settings) -> Integrator:
    return INTEGRATORS[settings.method](settings)


def camera_problem(settings: Settings, aperture_radius: float) -> str | None:
    """Why the method cannot render a camera with this lens, or None (checked when a job is
    submitted and again on the device)."""
    if INTEGRATORS[settings.method].pinhole_only and aperture_radius > 0.0:
        return f"method {settings.method} needs a pinhole camera (the scene's camera has a lens)"
    return None


__all__ = ["INTEGRATORS", "Delta", "Integrator", "camera_problem", "integrator_for"]
