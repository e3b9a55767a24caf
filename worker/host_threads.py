"""Host-side work spread over the machine's cores: a frame's per-pixel work (a fold round's
deltas, its error estimate) in independent pieces, one thread per core.

NumPy releases the GIL inside its loops and redis-py while it waits on a socket, so the
pieces run side by side; each writes only its own pixels, so the result is the same as
running them one after another, bit for bit.
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor
from typing import Callable, Iterable, TypeVar

T = TypeVar("T")
R = TypeVar("R")

# A thread per core, at most 4 (beyond, the memory bus limits); PHOTONFARM_HOST_THREADS sets it.
HOST_THREADS = max(1, int(os.environ.get("PHOTONFARM_HOST_THREADS", min(4, len(os.sched_getaffinity(0))))))
_PREFIX = "photonfarm-host"
_POOL = ThreadPoolExecutor(HOST_THREADS, thread_name_prefix=_PREFIX)


def each(work: Callable[[T], R], pieces: Iterable[T]) -> list[R]:
    """`work(piece)` for every piece, on the host threads; the results in order. Called from
    a host thread itself, it runs them there (a piece never waits on the pool)."""
    pieces = list(pieces)
    if HOST_THREADS == 1 or len(pieces) < 2 or threading.current_thread().name.startswith(_PREFIX):
        return [work(p) for p in pieces]
    return list(_POOL.map(work, pieces))
