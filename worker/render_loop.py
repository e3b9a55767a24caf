"""The progressive loop, in one place: the CLI, the tests and the benchmarks render with it.

Each pass is its own batch, run at the radii (or other inputs) the state gives after the
previous merge: the sequential progressive estimate of the dissertation. The service runs
the same integrator methods, batch by batch, on many workers (worker/tasks.py).
"""

from __future__ import annotations

import time
from collections.abc import Callable

from worker.engine import Engine
from worker.integrators.base import State

# Called after every merge with the state and the render seconds so far (the observer's
# own time excluded); returning True stops the loop.
Progress = Callable[[State, float], bool | None]


def render(engine: Engine, passes: int | None = None, seconds: float | None = None,
           progress: Progress | None = None, state: State | None = None) -> State:
    """Render until `state` has `passes` passes merged, `seconds` of rendering have passed,
    or `progress` says stop, whichever comes first. Starts a new state unless one is given
    (which is updated in place, so an interrupted caller keeps what was merged)."""
    if passes is None and seconds is None:
        raise ValueError("give passes, seconds or both")
    state = engine.start() if state is None else state
    start = time.perf_counter()
    observing = 0.0
    while True:
        elapsed = time.perf_counter() - start - observing
        if (passes is not None and state.passes >= passes) or (seconds is not None and elapsed >= seconds):
            return state
        delta = engine.render_batch(state, state.passes, 1)
        t0 = time.perf_counter()
        engine.integrator.merge(state, delta)
        engine.times.add_seconds("merge", time.perf_counter() - t0)
        del delta  # its sums view the engine's buffer: let the next batch sum into it again (Device.batch_sums)
        if progress is not None:
            t0 = time.perf_counter()
            stop = progress(state, t0 - start - observing)
            observing += time.perf_counter() - t0
            if stop:
                return state
