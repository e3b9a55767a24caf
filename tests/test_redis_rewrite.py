"""The embedded Redis's append-only-file rewrite runs below the API's priority
(service/redis_server.py, AOF_REWRITE_NICE): its forked child is made nicer than Redis
within AOF_REWRITE_CHECK_SECONDS of the fork."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from service.redis_server import AOF_REWRITE_CHECK_SECONDS, AOF_REWRITE_NICE, child_pids, lower_children
from tests.embedded_redis import holding

LINUX = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc/PID/task/PID/children (Linux)")


@LINUX
def test_lower_children_makes_each_child_nicer_than_its_parent() -> None:
    """A process that forks a child: the child ends AOF_REWRITE_NICE nicer than the parent,
    the parent as it was, and lowering again changes nothing."""
    parent = subprocess.Popen([sys.executable, "-c", "import os, time\nos.fork()\ntime.sleep(30)"])
    try:
        deadline = time.monotonic() + 10
        while not child_pids(parent.pid) and time.monotonic() < deadline:
            time.sleep(0.01)
        (child,) = child_pids(parent.pid)
        base = os.getpriority(os.PRIO_PROCESS, parent.pid)
        assert os.getpriority(os.PRIO_PROCESS, child) == base
        for _ in range(2):
            lower_children(parent.pid, AOF_REWRITE_NICE)
            assert os.getpriority(os.PRIO_PROCESS, child) == min(19, base + AOF_REWRITE_NICE)
            assert os.getpriority(os.PRIO_PROCESS, parent.pid) == base
    finally:
        parent.kill()
        parent.wait()
        subprocess.run(["pkill", "-P", str(parent.pid)], check=False)


@LINUX
def test_a_rewrite_child_of_the_embedded_redis_is_niced(tmp_path: Path) -> None:
    """8 values in the embedded Redis, then BGREWRITEAOF, the server told to take 0.25 s a
    key when it writes its data set (`rdb-key-save-delay`, Redis's own testing knob), so
    the rewrite lasts 2 s on any machine: its child, watched while it lives, reaches
    Redis's niceness + AOF_REWRITE_NICE within a few check intervals."""
    with holding(tmp_path, 8, 1 << 20, extra_config=("rdb-key-save-delay 250000",)) as (server, client):
        base = os.getpriority(os.PRIO_PROCESS, server.proc.pid)
        client.bgrewriteaof()
        first_seen: dict[int, float] = {}
        seen: dict[int, list[tuple[float, int]]] = {}  # child -> (seconds since first seen, niceness)
        start = time.monotonic()
        while time.monotonic() - start < 60:
            for child in child_pids(server.proc.pid):
                try:
                    niceness = os.getpriority(os.PRIO_PROCESS, child)
                except OSError:
                    continue  # it exited since
                now = time.monotonic()
                seen.setdefault(child, []).append((now - first_seen.setdefault(child, now), niceness))
            info = client.info("persistence")
            if seen and not info["aof_rewrite_in_progress"] and not info["aof_rewrite_scheduled"]:
                break
            time.sleep(0.02)
        assert seen, "no rewrite child was seen"
        lowered = [n for samples in seen.values() for at, n in samples if n == base + AOF_REWRITE_NICE]
        late = [(at, n) for samples in seen.values() for at, n in samples if at > 5 * AOF_REWRITE_CHECK_SECONDS]
        assert late, f"the rewrite ended within {5 * AOF_REWRITE_CHECK_SECONDS} s: {seen}"
        assert lowered and all(n == base + AOF_REWRITE_NICE for _, n in late), seen
        assert os.getpriority(os.PRIO_PROCESS, server.proc.pid) == base  # Redis itself is not lowered
