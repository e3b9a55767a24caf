"""A job's fold held in the folder's memory between checkpoints.

A fold round adds the accepted batches' deltas to the state in the folder process's memory
and writes the state back to the tiles only now and then, a part at a time (a checkpoint
of some tiles: policy.checkpoint_tiles), because writing the state is most of what a round
costs the state node (its bytes in, its append-only file, that file's rewrites). Between
checkpoints nothing durable changes but the batch inputs: the folded batches stay accepted
and not folded (`tofold`) until every tile has written them, their deltas stay pending on
the tiles that have not, the record's folded counters stay as the last complete batch left
them. So a folder that dies loses only work; the next folder folds the same batches again
from the tiles (TiledState.fold_round: a tile that wrote a batch skips it).

An overlay is valid while every tile still has the version it was built on: a checkpoint
by another folder bumps them, and the overlay is then dropped. This process's own
checkpoint writes the overlay's state, so readers keep it while the versions move
(`Overlays.writing`), and it goes on, on the new versions, with the batches some tile still
lacks.

A reader may use a state it was given as it is: a published state changes only where no
one else holds it. The next round adds to the overlay's own state in place when nothing but
the overlay refers to it or to its arrays (no reader is using it, `Overlays.merging`), and
the job's readers wait for the round (at 3840x2160 a copy was a tenth of a round's CPU and a
second GB of the folder's memory); while a reader holds it the round adds to a copy."""

from __future__ import annotations

import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

from worker.integrators import Integrator
from worker.integrators.base import State
from worker.store import policy
from worker.store.tiles import Tiling


@dataclass(frozen=True)
class Overlay:
    versions: dict[int, int]  # tile -> version the overlay was built on (its last checkpoint)
    batches: frozenset[str]  # accepted batches folded here that some tile has not written
    state: State  # the tiles' states with those batches added
    error: float | None  # the image's estimated error in `state`
    sent: dict[int, frozenset[str]]  # per tile, the arrays its pending deltas of them carried
    pending: dict[int, int]  # per tile, the bytes of those deltas it still holds
    folded_at: dict[str, float]  # per batch of them, time.monotonic() when it was folded here

    def state_bytes(self, tiling: Tiling) -> dict[int, int]:
        """Each tile's bytes of the state."""
        per_pixel = sum(a.nbytes // len(a) for a in self.state.arrays().values())
        return {k: per_pixel * (tiling.span(k).stop - tiling.span(k).start) for k in range(tiling.count)}

    def checkpoint_tiles(self, tiling: Tiling) -> list[int]:
        """The tiles a round that made this overlay writes (policy.checkpoint_tiles)."""
        oldest = min(self.folded_at.values(), default=time.monotonic())
        return policy.checkpoint_tiles(time.monotonic() - oldest, self.pending, self.state_bytes(tiling))

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
        self._merging: dict[str, int] = {}  # jobs whose overlay's state a round adds to in place -> its thread
        self._lock = threading.Lock()
        self._merged = threading.Condition(self._lock)  # a round that merged in place is done

    def valid(self, job_id: str, versions: dict[int, int]) -> Overlay | None:
        """The job's overlay if it was built on these tile versions, or this process is
        writing it to the tiles; a stale one is dropped. While another thread's round adds
        to the overlay's state in place, it waits for that round's overlay."""
        with self._lock:
            return self._valid(job_id, versions)

    def state(self, job_id: str, versions: dict[int, int]) -> State | None:
        """The valid overlay's state, for a reader: taken under the lock, so a round that
        would add to it in place sees the reader's reference (`merging`)."""
        with self._lock:
            overlay = self._valid(job_id, versions)
            return overlay.state if overlay is not None else None

    def _valid(self, job_id: str, versions: dict[int, int]) -> Overlay | None:
        me = threading.get_ident()
        self._merged.wait_for(lambda: self._merging.get(job_id, me) == me)
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

    @contextmanager
    def merging(self, job_id: str, overlay: Overlay, integrator: Integrator) -> Iterator[State]:
        """The state a round adds its batches to, made from `overlay` (the job's, valid):
        the overlay's own, changed in place, if nothing but the overlay refers to it or to
        one of its arrays, and the job's readers (`valid`) then wait until the round put
        its overlay; else a copy. A round that fails after changing the overlay's state
        drops the overlay (its state no longer matches it): the next reads the tiles."""
        with self._lock:
            in_place = self._items.get(job_id) is overlay and _unshared(overlay.state, integrator.setup_arrays)
            if in_place:
                self._merging[job_id] = threading.get_ident()
        try:
            yield overlay.state if in_place else overlay.copy_state(integrator)
        except BaseException:
            if in_place:
                self.drop(job_id)
            raise
        finally:
            if in_place:
                with self._lock:
                    del self._merging[job_id]
                    self._merged.notify_all()

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


def _unshared(state: State, setup: tuple[str, ...]) -> bool:
    """Nothing but its overlay refers to the state, nor to one of the arrays a merge adds
    to (all but the setup arrays; a view counts: it refers to its base). getrefcount counts
    its own argument too; the state's other references here are the overlay's and this
    call's, an array's the state's, this list's and the loop's."""
    merged = [a for name, a in state.arrays().items() if name not in setup]
    return sys.getrefcount(state) == 3 and all(sys.getrefcount(a) == 4 for a in merged)


OVERLAYS = Overlays()
