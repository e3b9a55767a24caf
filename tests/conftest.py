"""Shared fixtures: one OpenCL context per test session (the program is built once for it)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyopencl as cl
import pytest

from kernels.program import create_context
from worker.engine import Engine, RenderSettings
from worker.scene import bundled_scene_path, load_any_scene
from worker.stats import Accumulators


@pytest.fixture(scope="session")
def ctx() -> cl.Context:
    return create_context()


@pytest.fixture(scope="session")
def make_engine(ctx: cl.Context):
    """Engine for a bundled scene (by name) or a scene file (Path: our JSON or Mitsuba XML)."""

    def make(scene: str | Path, resolution: tuple[int, int] | None = None, **settings: object) -> Engine:
        path = scene if isinstance(scene, Path) else bundled_scene_path(scene)
        parsed, base = load_any_scene(path)
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
