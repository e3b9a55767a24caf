"""Host-side work in independent pieces (a fold round's deltas a tile at a time, its error
estimate a block at a time), optionally spread over threads.

NumPy releases the GIL inside its loops and redis-py while it waits on a socket, so the
pieces can run side by side; each writes only its own pixels, so the result is the same as
running them one after another, bit for bit.

One thread unless PHOTONFARM_HOST_THREADS says more. On this machine kind (2 cores) a
second thread never shortened a fold round (1920x1080: 0.72 against 0.76 s; 3840x2160:
4.72 against 4.70 s) and cost a 1920x1080 round 30% more CPU (0.45 against 0.59 s;
`bench.fold_round`; the error estimate alone 0.11 against 0.16-0.20 s): the pieces are
memory-bound and trade the GIL back and forth. Where the API shares the cores with
workers (`photonfarm serve`) that CPU comes out of rendering; an API on a machine of its
own with more cores and memory channels may set more threads.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable, Iterable
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

T = TypeVar("T")
R = TypeVar("R")

HOST_THREADS = max(1, int(os.environ.get("PHOTONFARM_HOST_THREADS", "1")))
_PREFIX = "photonfarm-host"
_POOL = ThreadPoolExecutor(HOST_THREADS, thread_name_prefix=_PREFIX)


def each(work: Callable[[T], R], pieces: Iterable[T]) -> list[R]:
    """`work(piece)` for every piece, on the host threads; the results in order. Called from
    a host thread itself, it runs them there (a piece never waits on the pool)."""
    pieces = list(pieces)
    if HOST_THREADS == 1 or len(pieces) < 2 or threading.current_thread().name.startswith(_PREFIX):
        return [work(p) for p in pieces]
    return list(_POOL.map(work, pieces))
