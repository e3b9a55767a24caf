"""Shared fixtures: one OpenCL context per test session (the program is built once for it),
a configuration with changed tunables, a real Redis of the test's own, and the deltas of the sharded-state tests."""

from __future__ import annotations

import dataclasses
import pickle
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pyopencl as cl
import pytest

from kernels.program import create_context
from service.redis_server import EmbeddedRedis
from tests.helpers import BATCHES, H, W
from worker import config as config_module
from worker.config import Config, config
from worker.engine import Engine
from worker.error_estimate import ErrorEstimate
from worker.integrators.base import State
from worker.integrators.photon_mapping import GatherInputs
from worker.render_loop import render as render_passes
from worker.scene import bundled_scene_path, inline_meshes, load_any_scene, load_scene_file
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


@pytest.fixture
def tune(monkeypatch: pytest.MonkeyPatch) -> Callable[..., Config]:
    """Install this process's configuration with the given fields changed, for this test."""
    def change(**fields: object) -> Config:
        changed = dataclasses.replace(config(), **fields)
        monkeypatch.setattr(config_module, "_active", changed)
        return changed
    return change


@pytest.fixture
def redis_url(tmp_path: Path) -> Iterator[str]:
    """A real embedded Redis of the test's own, stopped after it (api_tests/conftest.py
    takes this fixture too)."""
    server = EmbeddedRedis(tmp_path / "redis").start(supervise=False)
    yield server.url
    server.stop()


@pytest.fixture(scope="module")
def deltas(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict, Settings, np.ndarray]:
    """BATCHES deltas of 2 passes of the W x H cornell-caustics scene, at radii shrinking
    from R0, pickled to a file (for worker processes); with the inlined scene, the settings
    and R0 (tests/helpers.py's sharded setup)."""
    parsed, base = load_scene_file(bundled_scene_path("cornell-caustics"))
    settings = Settings(photons_per_pass=1 << 14, seed=21, resolution=(W, H))
    engine = Engine(parsed, base, settings)
    r0 = engine.start().R0
    made = [engine.run_batch(GatherInputs(r0 * (1.0 - 0.03 * i)), 2 * i, 2) for i in range(BATCHES)]
    path = tmp_path_factory.mktemp("deltas") / "deltas.pkl"
    path.write_bytes(pickle.dumps(made))
    return path, inline_meshes(parsed, base), settings, r0


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
