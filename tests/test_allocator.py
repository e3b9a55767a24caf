"""The C heap settings (worker/allocator.py): a freed frame-sized array's memory is reused by
the next one, in the process's threads too, rather than mapped and faulted in afresh; the
embedded redis-server gets the same settings, and its append-only file's pages leave the
page cache once written. Page faults and cached pages are counted by the kernel (minor
faults, mincore), so the tests do not depend on the machine's speed."""

from __future__ import annotations

import ctypes
import mmap
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest
import redis

from service.redis_server import AOF_DIR, AOF_FILE, AOF_PAGE_DROP_SECONDS, EmbeddedRedis
from tests.embedded_redis import holding
from worker import allocator

FRAME = 3840 * 2160  # float64 pixels: 66 MB, above glibc's largest default mmap threshold
PAGES = FRAME * 8 // 4096

# In a fresh process: one frame-sized array made and freed (its first touch faults in any
# case), then the faults of making and using the next one, on the main thread and on
# another.
SCRIPT = f"""
import resource, sys, threading
import numpy as np
from worker.allocator import retain_large_allocations
if sys.argv[1] == "retain":
    assert retain_large_allocations()
def faults():
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    (np.ones({FRAME}) * 2.0).sum()
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before
np.ones({FRAME}).sum()
out = [faults()]
t = threading.Thread(target=lambda: out.append(faults()))
t.start(); t.join()
print(*out)
"""


LINUX = pytest.mark.skipif(not sys.platform.startswith("linux"),
                           reason="the kernel's own counts as Linux gives them (minor faults, prctl, mincore)")
PR_SET_THP_DISABLE, PR_GET_THP_DISABLE = 41, 42  # linux/prctl.h


@contextmanager
def _small_pages() -> Iterator[None]:
    """Transparent huge pages off for this process and the processes it starts meanwhile
    (the flag is inherited across fork and exec, and overrides madvise), so that a fault
    is a 4 KiB page whatever the machine's huge-page mode."""
    libc = ctypes.CDLL(None, use_errno=True)
    before = libc.prctl(PR_GET_THP_DISABLE, 0, 0, 0, 0)
    assert libc.prctl(PR_SET_THP_DISABLE, 1, 0, 0, 0) == 0, os.strerror(ctypes.get_errno())
    try:
        yield
    finally:
        libc.prctl(PR_SET_THP_DISABLE, before, 0, 0, 0)


def _faults(mode: str) -> list[int]:
    with _small_pages():
        run = subprocess.run([sys.executable, "-c", SCRIPT, mode], capture_output=True, text=True, check=True,
                             cwd=Path(__file__).resolve().parents[1])
    return [int(x) for x in run.stdout.split()]


@LINUX
def test_a_freed_frame_is_reused_without_page_faults_on_every_thread() -> None:
    default, retained = _faults("default"), _faults("retain")
    # Without the settings each array (and the product's temporary) is mapped afresh: every page faults.
    assert min(default) > PAGES, default
    # With them the heap's freed memory is reused: a few pages (Python's own), not the frame.
    assert max(retained) < PAGES // 20, retained


def _redis_faults(env: dict[str, str]) -> int:
    """Minor faults of an embedded redis-server while it stores, serves and drops four 64 MB
    values (a worker's push, the folder's read, the fold's drop)."""
    with tempfile.TemporaryDirectory() as tmp:
        server = EmbeddedRedis(Path(tmp))
        server_env = allocator.environment
        allocator.environment = lambda: env  # the settings the server is started with
        try:
            with _small_pages():
                server.start(supervise=False)
        finally:
            allocator.environment = server_env
        try:
            client = redis.Redis.from_url(server.url)
            blob = os.urandom(64 << 20)
            client.set("x", blob)
            client.delete("x")
            for _ in range(5):  # a window the server forked in (an append-only-file rewrite) counts
                while client.info("persistence")["aof_rewrite_in_progress"]:  # the child's copy-on-write
                    time.sleep(0.05)  # faults, not the allocator's: it is measured again
                forks, before = client.info("stats")["total_forks"], _minflt(server.proc.pid)
                for _ in range(4):
                    client.set("x", blob)
                    client.get("x")
                    client.delete("x")
                faults = _minflt(server.proc.pid) - before
                if client.info("stats")["total_forks"] == forks:
                    break
            return faults
        finally:
            server.stop()


def _minflt(pid: int) -> int:
    return int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[7])


@LINUX
def test_the_embedded_redis_reuses_a_dropped_value() -> None:
    """Each value a worker pushes is held, read, then dropped once folded: with the settings,
    the next one takes its memory."""
    pages = 4 * (64 << 20) // 4096
    default, retained = _redis_faults({}), _redis_faults(allocator.environment())
    assert default > 2 * pages, default
    assert retained < default / 2, (retained, default)


def _cached_share(path: Path) -> float:
    """The share of a file's pages in the page cache (mincore of a mapping, which reads none)."""
    libc = ctypes.CDLL(None, use_errno=True)
    libc.mmap.restype = ctypes.c_void_p
    libc.mmap.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int, ctypes.c_int, ctypes.c_int, ctypes.c_long]
    libc.mincore.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_void_p]
    libc.munmap.argtypes = [ctypes.c_void_p, ctypes.c_size_t]
    size = path.stat().st_size
    pages = -(-size // mmap.PAGESIZE)
    with open(path, "rb") as f:
        addr = libc.mmap(None, size, mmap.PROT_READ, mmap.MAP_SHARED, f.fileno(), 0)
    assert addr not in (None, ctypes.c_void_p(-1).value), os.strerror(ctypes.get_errno())
    try:
        vec = (ctypes.c_ubyte * pages)()
        assert libc.mincore(addr, size, vec) == 0, os.strerror(ctypes.get_errno())
        return sum(v & 1 for v in vec) / pages
    finally:
        libc.munmap(addr, size)


def _part_sizes(folder: Path) -> dict[str, int]:
    """The append-only file's parts and their sizes (a part a rewrite removed meanwhile is left out)."""
    sizes = {}
    for f in folder.glob(f"{AOF_FILE}*"):
        try:
            sizes[f.name] = f.stat().st_size
        except FileNotFoundError:
            continue
    return sizes


@LINUX
def test_the_append_only_file_leaves_the_page_cache(tmp_path: Path) -> None:
    """128 MB of values go through the embedded server's append-only file (its parts in
    AOF_DIR); within a few drop intervals at most a tenth of any part is still cached (a file just written is
    cached whole)."""
    def shares() -> dict[str, float]:  # listed anew each time: a rewrite replaces the parts
        out = {}
        for name, size in _part_sizes(tmp_path / AOF_DIR).items():
            try:
                out[name] = _cached_share(tmp_path / AOF_DIR / name) if size else 0.0
            except FileNotFoundError:
                continue
        return out

    with holding(tmp_path, 8, 16 << 20):
        sizes = _part_sizes(tmp_path / AOF_DIR)
        assert sum(sizes.values()) >= 8 * (16 << 20), sizes
        deadline = time.monotonic() + 5 * AOF_PAGE_DROP_SECONDS
        while max(shares().values()) > 0.1 and time.monotonic() < deadline:
            time.sleep(0.1)
        assert max(shares().values()) <= 0.1, shares()
