"""Host-side work in independent pieces (a fold round's deltas a tile at a time, its error
estimate a block at a time), optionally spread over threads.

NumPy releases the GIL inside its loops and redis-py while it waits on a socket, so the
pieces can run side by side; each writes only its own pixels, so the result is the same as
running them one after another, bit for bit.

One thread unless PHOTONFARM_HOST_THREADS says more: the pieces are memory-bound and trade
the GIL back and forth, so on a few cores a second thread costs CPU (which, where the API
shares the cores with workers, comes out of rendering) without shortening a round. An
API on a machine of its own with more cores and memory channels may set more threads.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterable
from concurrent.futures import ThreadPoolExecutor
from functools import cache
from typing import TypeVar

from worker.config import config

T = TypeVar("T")
R = TypeVar("R")

_PREFIX = "photonfarm-host"


def threads() -> int:
    return max(1, config().host_threads)


@cache
def _pool() -> ThreadPoolExecutor:
    return ThreadPoolExecutor(threads(), thread_name_prefix=_PREFIX)


def each(work: Callable[[T], R], pieces: Iterable[T]) -> list[R]:
    """`work(piece)` for every piece, on the host threads; the results in order. Called from
    a host thread itself, it runs them there (a piece never waits on the pool)."""
    pieces = list(pieces)
    if threads() == 1 or len(pieces) < 2 or threading.current_thread().name.startswith(_PREFIX):
        return [work(p) for p in pieces]
    return list(_pool().map(work, pieces))
