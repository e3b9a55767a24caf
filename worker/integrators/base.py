"""The integrator interface: what a rendering method traces per pass, which additive
per-pixel sums it returns, and how its image and error estimate are formed from them.

A method is two halves. The host half (this interface, no OpenCL) is all the service,
the job store and the merge ever see: the sums' layout, the job state, `merge`, `image`
and `estimate`. The device half (`Passes`, imported only where rendering happens) runs
the kernels of a batch of passes and returns the batch's sums. Adding a method means one
subclass of each, registered in worker/integrators/__init__.py; nothing in service/ and
nothing in the store's merge changes, because both only call these methods and store
the named arrays the integrator declares.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, ClassVar, Generic, Protocol, TypeVar

import numpy as np

from kernels.contract import SumLayout
from worker.error_estimate import ErrorEstimate
from worker.settings import Settings
from worker.stats import add_counts


@dataclass
class Delta:
    """What a batch of passes adds to a job: its per-pixel sums (float64) and counters."""

    first_pass: int
    n_passes: int
    emitted: int  # photon paths emitted over the batch
    sums: dict[str, np.ndarray]  # every name of the integrator's SumLayout
    # Scalar integer counters the job state sums as it sums `emitted` (e.g. the adaptive
    # sampler's uniform draws, worker/adaptive.py); a name missing counts as 0.
    counters: dict[str, int] = field(default_factory=dict)

    def __getattr__(self, name: str) -> np.ndarray:
        sums = self.__dict__.get("sums")  # (no recursion while unpickling, before `sums` exists)
        if sums is not None and name in sums:
            return sums[name]
        raise AttributeError(name)


class State(Protocol):
    """A job's progressive state, as the store keeps it: named per-pixel arrays and counters."""

    sums: dict[str, np.ndarray]  # the integrator's additive per-pixel sums
    emitted: int
    passes: int
    counters: dict[str, int]  # summed like `emitted` (Delta.counters)

    def arrays(self) -> dict[str, np.ndarray]: ...


StateT = TypeVar("StateT", bound=State)


class Integrator(ABC, Generic[StateT]):
    """The host half of a rendering method (see the module docstring), over its own state
    type `StateT`: every method taking a state takes the one `start` and `restore` make."""

    name: ClassVar[str]
    program: ClassVar[str] = "photon_mapping"  # the OpenCL program it runs (kernels/program.py, PROGRAMS)
    # Per-pixel arrays fixed once per job by its first batch (first writer wins), e.g. R0.
    setup_arrays: ClassVar[tuple[str, ...]] = ()
    # The dataclass of per-pixel arrays `batch_inputs` returns (None: a batch reads nothing);
    # the store keeps it per tile and rebuilds it for a batch.
    inputs_type: ClassVar[type | None] = None

    def __init__(self, settings: Settings) -> None:
        self.settings = settings

    @property
    def alpha(self) -> float:
        """The radius exponent alpha; Settings fills it by method when a job leaves it out."""
        alpha = self.settings.alpha
        if alpha is None:
            raise ValueError("settings without alpha: build them through Settings, which fills it by method")
        return alpha

    @property
    @abstractmethod
    def sums(self) -> SumLayout:
        """The additive per-pixel sums a batch returns (and the kernels' record layout)."""

    @property
    @abstractmethod
    def state_widths(self) -> dict[str, int]:
        """Every per-pixel array of the job state (setup arrays and sums included) and its width."""

    @abstractmethod
    def start(self, setup: dict[str, np.ndarray]) -> StateT:
        """The empty state of a job whose setup arrays (`setup_arrays`) are fixed."""

    @abstractmethod
    def restore(self, arrays: dict[str, np.ndarray], emitted: int, passes: int,
                counters: dict[str, int] | None = None) -> StateT:
        """The job state from stored arrays (setup arrays present, missing sums zero) and counters."""

    @abstractmethod
    def batch_inputs(self, state: StateT) -> Any:
        """What a batch starting now reads from the state (an `inputs_type`, or None)."""

    def merge(self, state: StateT, delta: Delta) -> None:
        """Add a batch to the state: commutative in every sum."""
        self.merge_sums(state, delta.sums)
        add_counts(state, delta.n_passes, delta.emitted, delta.counters)

    @abstractmethod
    def merge_sums(self, state: StateT, sums: dict[str, np.ndarray], pixels: slice = slice(None)) -> None:
        """The per-pixel part of `merge` over a run of pixels (`sums`: the arrays of those
        pixels a delta carries; one it lacks is zero). A fold round adds each tile's
        deltas this way, straight into the state, with `add_counts` once for the batches."""

    @abstractmethod
    def image(self, state: StateT) -> np.ndarray:
        """The current estimate, (pixels, 3) float64."""

    @abstractmethod
    def estimate(self, state: StateT) -> ErrorEstimate | None:
        """The per-pixel error bound and its image average (dissertation ch. 6); None when
        the job does not estimate its error (`error_estimation` off)."""

    def notes(self, counters: dict[str, int]) -> list[str]:
        """What the method decided from a job's merged counters, one line each (a job's
        view lists them after its scene's notes); none by default."""
        return []


KeepGoing = Callable[[int], bool]


class BatchAborted(Exception):
    """A batch stopped between passes because its job no longer wants it."""


class Passes(Protocol):
    """The device half of a method: runs a batch of passes on one engine."""

    def setup(self) -> dict[str, np.ndarray]:
        """The job's setup arrays (e.g. R0), computed on the device from pass 0."""

    def run_batch(self, inputs: Any, first_pass: int, n_passes: int, keep_going: KeepGoing | None = None) -> Delta:
        """Passes first_pass .. first_pass + n_passes - 1; `keep_going(pass)` is asked after
        every pass, and False raises BatchAborted."""
