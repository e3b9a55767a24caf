"""Shared fixtures: one OpenCL context per test session (the program is built once for it)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyopencl as cl
import pytest

from kernels.program import create_context
from worker.engine import Engine, RenderSettings
from worker.error_estimate import ErrorEstimate, bias_estimate, estimate
from worker.scene import bundled_scene_path, load_scene_file
from worker.stats import Accumulators


@pytest.fixture(scope="session")
def ctx() -> cl.Context:
    return create_context()


@pytest.fixture(scope="session")
def make_engine(ctx: cl.Context):
    """Engine for a bundled scene (by name) or a scene file (Path)."""

    def make(scene: str | Path, resolution: tuple[int, int] | None = None, **settings: object) -> Engine:
        path = scene if isinstance(scene, Path) else bundled_scene_path(scene)
        parsed, base = load_scene_file(path)
        return Engine(parsed, base, RenderSettings(**settings), resolution=resolution, ctx=ctx)

    return make


def render(engine: Engine, passes: int, alpha: float = 0.7) -> Accumulators:
    """Sequential progressive render: one pass per batch, each at the current radii."""
    state = Accumulators.start(alpha, engine.initial_radius())
    for k in range(passes):
        state.merge(engine.run_batch(state.radius(), k, 1))
    return state


def image(engine: Engine, state: Accumulators) -> np.ndarray:
    return state.radiance().reshape(engine.arrays.height, engine.arrays.width, 3)


def render_until(engine: Engine, threshold: float, confidence: float = 0.9, max_passes: int = 1000,
                 alpha: float = 0.7) -> tuple[Accumulators, ErrorEstimate]:
    """The progressive loop with termination: one pass per batch, the variance samples
    bias-corrected (eq. 6.22), until the estimated average relative error is at most
    `threshold` or `max_passes` ran."""
    state = Accumulators.start(alpha, engine.initial_radius())
    est = estimate(state, confidence)
    while est.average > threshold and state.passes < max_passes:
        r = state.radius()
        state.merge(engine.run_batch(r, state.passes, 1, bias=bias_estimate(r, state.G, state.emitted, "taylor")))
        est = estimate(state, confidence)
    return state, est
