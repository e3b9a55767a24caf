"""The device halves of the integrators, by name (imported only where rendering happens)."""

from __future__ import annotations

from typing import TYPE_CHECKING

from worker.integrators.base import Integrator, Passes
from worker.integrators.connect_merge import ConnectMerge
from worker.integrators.connect_merge_passes import ConnectMergePasses
from worker.integrators.photon_mapping import PhotonMapping
from worker.integrators.photon_mapping_passes import PhotonMappingPasses

if TYPE_CHECKING:
    from worker.engine import Device


def passes_for(integrator: Integrator, device: Device) -> Passes:
    if isinstance(integrator, PhotonMapping):
        return PhotonMappingPasses(integrator, device)
    if isinstance(integrator, ConnectMerge):
        return ConnectMergePasses(integrator, device)
    raise ValueError(f"no device half for method {integrator.name!r}")
