"""Shared fixtures: one OpenCL context per test session (the program is built once for it)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyopencl as cl
import pytest

from kernels.program import create_context
from worker.engine import Engine
from worker.error_estimate import ErrorEstimate
from worker.integrators.base import State
from worker.render_loop import render as render_passes
from worker.scene import bundled_scene_path, load_any_scene
from worker.settings import Settings


@pytest.fixture(scope="session")
def ctx() -> cl.Context:
    return create_context()


@pytest.fixture(scope="session")
def make_engine(ctx: cl.Context):
    """Engine for a bundled scene (by name) or a scene file (Path: our JSON or Mitsuba XML),
    with settings fields."""

    def make(scene: str | Path, resolution: tuple[int, int] | None = None, **settings: object) -> Engine:
        path = scene if isinstance(scene, Path) else bundled_scene_path(scene)
        parsed, base = load_any_scene(path)
        return Engine(parsed, base, Settings(resolution=resolution, **settings), ctx=ctx)

    return make


def render(engine: Engine, passes: int) -> State:
    """Sequential progressive render (worker/render_loop.py): one pass per batch."""
    return render_passes(engine, passes=passes)


def image(engine: Engine, state: State) -> np.ndarray:
    return engine.integrator.image(state).reshape(engine.arrays.height, engine.arrays.width, 3)


def render_until(engine: Engine, threshold: float, max_passes: int) -> tuple[State, ErrorEstimate]:
    """The progressive loop with termination, as a job with `error_threshold` runs it: stop
    once the estimated average relative error (at the engine's confidence) is at most
    `threshold`, or after `max_passes`."""
    state = render_passes(engine, passes=max_passes,
                          progress=lambda st, _: engine.integrator.estimate(st).average <= threshold)
    return state, engine.integrator.estimate(state)
