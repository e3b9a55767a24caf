"""A job's fold held in the folder's memory between checkpoints.

A fold round adds the accepted batches' deltas to the state in the folder process's memory
and writes the state back to the tiles only now and then (a checkpoint: policy.
checkpoint_due), because writing the whole state is most of what a round costs the state
node (its bytes in, its append-only file, that file's rewrites). Between checkpoints
nothing durable changes but the batch inputs: the folded batches stay accepted and not
folded (`tofold`), their deltas stay pending on the tiles, the record's folded counters and
the tiles' folded sets stay as the last checkpoint left them. So a folder that dies loses
only work; the next folder folds the same batches again from the last checkpoint.

An overlay is valid while every tile still has the version it was built on: a checkpoint
by another folder bumps them, and the overlay is then dropped. This process's own
checkpoint writes the overlay's state, so readers keep it while the versions move
(`Overlays.writing`), and it goes on, on the new versions, with no batch pending. Its state
is never changed once published (a round copies it before adding to it), so readers may use
it as it is."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

from worker.integrators import Integrator
from worker.integrators.base import State
from worker.store import policy


@dataclass(frozen=True)
class Overlay:
    versions: dict[int, int]  # tile -> version the overlay was built on (its last checkpoint)
    batches: frozenset[str]  # accepted batches folded here since then
    state: State  # the checkpoint's state with those batches added
    error: float | None  # the image's estimated error in `state`
    sent: dict[int, frozenset[str]]  # per tile, the arrays those batches' deltas carried
    pending_bytes: int  # their deltas' bytes the tiles still hold
    since: float  # time.monotonic() when the first of them was folded

    def checkpoint_due(self) -> bool:
        return policy.checkpoint_due(time.monotonic() - self.since, self.pending_bytes,
                                     sum(a.nbytes for a in self.state.arrays().values()))

    def copy_state(self, integrator: Integrator) -> State:
        """A state to add the next round to (this one stays as readers saw it)."""
        s = self.state
        return integrator.restore({name: a.copy() for name, a in s.arrays().items()}, s.emitted, s.passes,
                                  dict(s.counters))


class Overlays:
    """This process's overlays by job."""

    def __init__(self) -> None:
        self._items: dict[str, Overlay] = {}
        self._writing: set[str] = set()  # jobs whose overlay this process is writing to the tiles
        self._lock = threading.Lock()

    def valid(self, job_id: str, versions: dict[int, int]) -> Overlay | None:
        """The job's overlay if it was built on these tile versions, or this process is
        writing it to the tiles; a stale one is dropped."""
        with self._lock:
            overlay = self._items.get(job_id)
            if overlay is not None and overlay.versions != versions and job_id not in self._writing:
                del self._items[job_id]
                return None
            return overlay

    def current(self, job_id: str) -> Overlay | None:
        return self._items.get(job_id)

    @contextmanager
    def writing(self, job_id: str) -> Iterator[None]:
        """While this process writes the job's overlay to the tiles (and counts what it
        wrote): its readers keep the overlay though the tiles' versions move; dropped if the
        writing fails."""
        with self._lock:
            self._writing.add(job_id)
        try:
            yield
        except BaseException:
            self.drop(job_id)
            raise
        finally:
            with self._lock:
                self._writing.discard(job_id)

    def batches(self, job_id: str) -> frozenset[str]:
        overlay = self._items.get(job_id)
        return overlay.batches if overlay is not None else frozenset()

    def put(self, job_id: str, overlay: Overlay) -> None:
        with self._lock:
            self._items[job_id] = overlay

    def drop(self, job_id: str) -> None:
        with self._lock:
            self._items.pop(job_id, None)

    def keep_only(self, job_ids: set[str]) -> None:
        """Forget the overlays of other jobs (ended: their last round was a checkpoint)."""
        with self._lock:
            for job_id in [j for j in self._items if j not in job_ids]:
                del self._items[job_id]


OVERLAYS = Overlays()
