"""Child processes that end with their parent.

`photonfarm serve` owns its Redis and local workers. uvicorn re-raises SIGTERM after its
graceful shutdown, and a SIGKILL runs no Python at all, so cleanup code in the parent
cannot be relied on: the kernel's parent-death signal (Linux prctl PR_SET_PDEATHSIG)
ends each child when the thread that started it goes away."""

from __future__ import annotations

import ctypes
import signal
import subprocess
import sys
from typing import Any

_PR_SET_PDEATHSIG = 1


def _die_with_parent() -> None:
    libc = ctypes.CDLL("libc.so.6", use_errno=True)
    libc.prctl(_PR_SET_PDEATHSIG, signal.SIGTERM)


def spawn(args: list[str], **kwargs: Any) -> subprocess.Popen:
    """subprocess.Popen, plus: the child gets SIGTERM when its parent dies (on Linux)."""
    if sys.platform.startswith("linux"):
        kwargs["preexec_fn"] = _die_with_parent
    return subprocess.Popen(args, **kwargs)
