"""A worker on another host: its own network namespace, reaching Redis only over a veth
link. The job's scene is inline (no file of it exists anywhere) and the worker runs in an
empty directory, so the render can only have used what travelled through Redis."""

from __future__ import annotations

import math
import os
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest

from api_tests.cluster import Cluster, finished, merged_passes
from api_tests.helpers import decode_image


def _ip(*args: str) -> None:
    subprocess.run(["ip", *args], check=True, capture_output=True, text=True)


@pytest.fixture()
def remote_host() -> Iterator[tuple[str, str]]:
    """(namespace, host-side address): a /30 link between this host and the namespace."""
    tag = os.getpid() % 10_000
    ns, host_if, ns_if = f"pf-remote-{tag}", f"pfh{tag}", f"pfn{tag}"
    octet = 1 + tag % 250
    host_addr, ns_addr = f"10.231.{octet}.1", f"10.231.{octet}.2"
    try:
        _ip("netns", "add", ns)
    except (subprocess.CalledProcessError, FileNotFoundError) as exc:
        pytest.skip(f"this machine forbids network namespaces ({getattr(exc, 'stderr', exc)!s})")
    try:
        _ip("link", "add", host_if, "type", "veth", "peer", "name", ns_if)
        _ip("link", "set", ns_if, "netns", ns)
        _ip("addr", "add", f"{host_addr}/30", "dev", host_if)
        _ip("link", "set", host_if, "up")
        _ip("netns", "exec", ns, "ip", "addr", "add", f"{ns_addr}/30", "dev", ns_if)
        _ip("netns", "exec", ns, "ip", "link", "set", ns_if, "up")
        _ip("netns", "exec", ns, "ip", "link", "set", "lo", "up")
        yield ns, host_addr
    finally:
        subprocess.run(["ip", "link", "del", host_if], capture_output=True)
        subprocess.run(["ip", "netns", "del", ns], capture_output=True)


def test_worker_in_another_network_namespace(remote_host: tuple[str, str], tmp_path: Path) -> None:
    ns, host_addr = remote_host
    c = Cluster(tmp_path, workers=0, redis_bind=host_addr)  # Redis listens only on the link
    try:
        empty = tmp_path / "empty"
        empty.mkdir()
        worker = c.start_worker(prefix=["ip", "netns", "exec", ns], cwd=empty)
        scene = c.http.get("/v1/scenes/furnace").json()
        scene["materials"]["wall"]["albedo"] = [0.6, 0.6, 0.6]  # a scene that exists only in this request
        job = c.submit(scene=scene, settings={"max_passes": 12, "photons_per_pass": 1 << 15})
        done = c.wait(job["id"], finished, timeout=120)
        assert done["status"] == "completed" and done["passes"] == 12, done
        assert merged_passes(c.redis_client, job["id"]) == list(range(12))
        names = [w.decode() for w in c.redis_client.smembers("rq:workers")]
        assert any(f".{worker.pid}." in n for n in names), names  # the namespaced worker did it
        rho, phi = 0.6, 4 * math.pi
        mean = decode_image(c.http.get(job["links"]["image_exr"]).content, ".exr").mean()
        assert abs(mean / (rho * phi / (4 * math.pi ** 2 * (1 - rho))) - 1) < 0.03, mean
    finally:
        c.close()
