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


__all__ = ["INTEGRATORS", "Delta", "Integrator", "integrator_for"]
