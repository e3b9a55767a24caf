"""Child processes that end with their parent.

`photonfarm serve` owns its Redis and local workers. Its own shutdown stops them in
order (workers, then Redis), but a SIGKILL runs no Python at all, so the kernel's
parent-death signal (Linux prctl PR_SET_PDEATHSIG) is the backstop: each child gets
SIGTERM when the *thread* that started it ends, so children are started only from
threads that live as long as the process (the main thread, the daemon supervisors)."""

from __future__ import annotations

import ctypes
import functools
import os
import signal
import subprocess
import sys
from typing import Any

_PR_SET_PDEATHSIG = 1


def _die_with_parent(parent: int) -> None:
    libc = ctypes.CDLL("libc.so.6", use_errno=True)
    libc.prctl(_PR_SET_PDEATHSIG, signal.SIGTERM)
    if os.getppid() != parent:  # the parent died between fork and prctl: no signal will come
        os._exit(1)


def spawn(args: list[str], **kwargs: Any) -> subprocess.Popen:
    """subprocess.Popen, plus: the child gets SIGTERM when its parent dies (on Linux)."""
    if sys.platform.startswith("linux"):
        kwargs["preexec_fn"] = functools.partial(_die_with_parent, os.getpid())
    return subprocess.Popen(args, **kwargs)
