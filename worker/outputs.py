"""What a render writes: the image, its error estimate as layers of the same EXR, and
the facts that made it (passes, photons, seed, method, settings, error) as metadata."""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from worker.image_io import write_image

if TYPE_CHECKING:  # (the CLI checks its outputs without loading the engine)
    from worker.settings import Settings
    from worker.store.published import Published

ERROR_LAYERS = ("bias", "noise", "bound", "relative")  # luminance, per pixel (worker/error_estimate.py)


def make_folder(path: Path) -> None:
    """The folders `path` goes in, made if missing; ValueError with a one-line reason if they cannot be."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ValueError(f"cannot write {path}: {exc.strerror or exc}") from None


def check_writable(path: Path) -> None:
    """Fail before rendering (or waiting on a job), not after: make missing folders, and
    probe that the file can be written (ValueError with a one-line reason)."""
    make_folder(path)
    try:
        existed = path.exists()
        with open(path, "ab"):
            pass
        if not existed:
            path.unlink()
    except OSError as exc:
        raise ValueError(f"cannot write {path}: {exc.strerror or exc}") from None


def write_render(path: Path, settings: Settings, image: Published, width: int, height: int,
                 error_layers: bool = True) -> None:
    """An image (worker/store/published.py: the estimate and its error) to `path` (.png
    tone-mapped, .exr linear with metadata and, when the job estimates its error and
    `error_layers` is set, the layers error.bias, error.noise, error.bound and error.relative)."""
    rgb = image.rgb.reshape(height, width, 3)
    if Path(path).suffix.lower() != ".exr":
        write_image(path, rgb)
        return
    metadata: dict[str, object] = {"passes": image.passes, "photons": image.emitted, "seed": settings.seed,
                                   "method": settings.method, "settings": settings.model_dump_json()}
    if image.counters:  # SPPM's radius schedule held (worker/stats.py); the adaptive sampler's draws, splats, ...
        metadata["counters"] = json.dumps(image.counters, sort_keys=True)
    estimate = image.estimate if image.passes > 0 else None
    pixels = rgb
    channels: tuple[str, ...] = ("R", "G", "B")
    if estimate is not None:
        metadata.update(error_estimate=estimate.average, confidence=estimate.confidence)
        if error_layers:
            layers = np.stack([getattr(estimate, name) for name in ERROR_LAYERS], axis=-1).reshape(height, width, -1)
            pixels = np.concatenate([rgb, layers], axis=-1)
            channels += tuple(f"error.{name}" for name in ERROR_LAYERS)
    write_image(path, pixels, channels=channels, metadata=metadata)
