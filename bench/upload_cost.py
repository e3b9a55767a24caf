"""Upload cost: what a hostile upload of at most 1 MiB costs the API (issue 52, item 1).

    python -m bench.upload_cost [--concurrent 10] [--rounds 1]

A real cluster (api_tests/cluster.py: redis-server and the API under uvicorn, no workers)
receives one upload of each kind below, each at most 1 MiB on the wire, and records its
status, wall time and the CPU seconds of the API's whole process tree (the API process,
the scene loaders' forkserver and its load processes, and every child they reaped):
- include bomb: 1,000 includes per file, three files deep (1,000^3 inclusions if unbounded);
- element bomb: one XML file of 200,001 elements;
- deep nest: XML nested 100,000 deep;
- huge PLY declaration: a header declaring 10^9 vertices and faces over a short body;
- OBJ of 2,000,000 faces: past the triangle limit as declared;
- zip bomb: an archive that unpacks past the upload's byte limit;
- 60 MiB OBJ of comments: under the load's byte limit, so parsed;
- many mesh files: 2,000 shapes naming one small PLY;
- largest valid mesh: an OBJ of 500,000 triangles (accepted: a job is made, then deleted).
Then `--concurrent` uploads (the kinds above in turn) are sent at once while /healthz is
asked every 50 ms; its latencies while they are processed are recorded. Prints a table and
writes bench/out/upload_cost.json.
"""

from __future__ import annotations

import argparse
import io
import json
import tempfile
import threading
import time
import zipfile
from collections.abc import Callable
from pathlib import Path

import httpx
import numpy as np
import psutil

from api_tests.cluster import Cluster
from api_tests.helpers import zip_bomb
from bench.common import write_json
from worker.scene import SCENES_DIR

MITSUBA = SCENES_DIR / "mitsuba"
LIMIT_BYTES = 1 << 20  # the largest upload the bench sends
SETTINGS = {"max_passes": 1, "photons_per_pass": 1024, "resolution": [16, 16]}
HEALTH_EVERY = 0.05


def tree_cpu(pid: int) -> float:
    """CPU seconds of a process and its descendants, with the children each has reaped."""
    total = 0.0
    root = psutil.Process(pid)
    for proc in [root, *root.children(recursive=True)]:
        try:
            t = proc.cpu_times()
        except psutil.NoSuchProcess:  # ended between the listing and the read: its parent reaped it
            continue
        total += t.user + t.system + t.children_user + t.children_system
    return total


def _zip(entries: dict[str, bytes]) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED, compresslevel=9) as z:
        for name, data in entries.items():
            z.writestr(name, data)
    return buf.getvalue()


def _with_sensor(body: bytes) -> bytes:
    """ply-mesh.xml's sensor and room with `body` as the rest of the scene."""
    text = (MITSUBA / "ply-mesh.xml").read_bytes()
    start = text.index(b'<shape type="ply">')
    return text[:start] + body + b"\n</scene>\n"


def _room() -> dict[str, bytes]:
    return {"room.xml": (MITSUBA / "room.xml").read_bytes()}


def include_bomb() -> bytes:
    inc = b'<include filename="%s"/>'
    level = {f"i{k}.xml": b'<scene version="3.0.0">' + inc % f"i{k + 1}.xml".encode() * 1000 + b"</scene>"
             for k in (1, 2)}
    return _zip({"s.xml": _with_sensor(inc % b"i1.xml" * 1000), "i3.xml": b'<scene version="3.0.0"/>', **level,
                 **_room()})


def element_bomb() -> bytes:
    return _zip({"s.xml": _with_sensor(b'<default name="x" value="1"/>\n' * 200_001), **_room()})


def deep_nest() -> bytes:
    return _zip({"s.xml": _with_sensor(b'<shape type="sphere">' + b"<bsdf>" * 100_000 + b"</bsdf>" * 100_000
                                       + b"</shape>"), **_room()})


def _mesh_scene(name: str, mesh: bytes, shapes: int = 1) -> bytes:
    kind = name.rsplit(".", 1)[1].encode()
    shape = b'<shape type="%s"><string name="filename" value="%s"/><ref id="white"/></shape>\n' % (kind, name.encode())
    return _zip({"s.xml": _with_sensor(shape * shapes), name: mesh, **_room()})


def huge_ply_declaration() -> bytes:
    header = (b"ply\nformat binary_little_endian 1.0\nelement vertex 1000000000\nproperty float x\n"
              b"property float y\nproperty float z\nelement face 1000000000\n"
              b"property list uchar int vertex_indices\nend_header\n")
    return _mesh_scene("m.ply", header + bytes(4096))


def obj_past_the_triangle_limit() -> bytes:
    return _mesh_scene("m.obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\n" + b"f 1 2 3\n" * 2_000_000)


def comment_obj() -> bytes:
    line = b"# " + b"x" * 61 + b"\n"
    return _mesh_scene("m.obj", line * (60 * (1 << 20) // len(line)) + b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")


def many_mesh_files() -> bytes:
    return _mesh_scene("m.ply", (MITSUBA / "meshes" / "icosphere.ply").read_bytes(), shapes=2_000)


def largest_valid_mesh() -> bytes:
    return _mesh_scene("m.obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\n" + b"f 1 2 3\n" * 499_000)


CASES: dict[str, Callable[[], bytes]] = {
    "include bomb": include_bomb, "element bomb": element_bomb, "deep nest": deep_nest,
    "huge PLY declaration": huge_ply_declaration, "OBJ of 2,000,000 faces": obj_past_the_triangle_limit,
    "zip bomb": zip_bomb, "60 MiB OBJ of comments": comment_obj, "many mesh files": many_mesh_files,
    "largest valid mesh": largest_valid_mesh,
}


def upload(http: httpx.Client, archive: bytes) -> httpx.Response:
    return http.post("/v1/jobs/upload", files=[("archive", ("a.zip", archive))],
                     data={"scene": "s.xml", "settings": json.dumps(SETTINGS)}, timeout=300)


def _detail(resp: httpx.Response) -> str:
    if resp.status_code == 201:
        return "job created"
    detail = resp.json().get("detail")
    text = detail if isinstance(detail, str) else detail[0]["msg"] if detail else ""
    return text[:110]


class HealthPoller:
    """GET /healthz every HEALTH_EVERY seconds on its own connection, while inside `with`."""

    def __init__(self, c: Cluster) -> None:
        self.url = str(c.http.base_url)
        self.latencies: list[float] = []
        self.done = threading.Event()
        self.thread = threading.Thread(target=self._run)

    def _run(self) -> None:
        with httpx.Client(base_url=self.url, timeout=30) as http:
            while not self.done.is_set():
                t = time.monotonic()
                assert http.get("/healthz").status_code == 200
                self.latencies.append(time.monotonic() - t)
                time.sleep(HEALTH_EVERY)

    def __enter__(self) -> HealthPoller:
        self.thread.start()
        time.sleep(0.3)
        return self

    def __exit__(self, *_: object) -> None:
        self.done.set()
        self.thread.join()

    def summary(self) -> dict:
        arr = np.array(self.latencies or [float("nan")]) * 1000
        return {"healthz_n": len(self.latencies), "healthz_p50_ms": round(float(np.median(arr)), 1),
                "healthz_p99_ms": round(float(np.percentile(arr, 99)), 1), "healthz_max_ms": round(float(arr.max()), 1)}


def one(c: Cluster, name: str, archive: bytes) -> dict:
    with HealthPoller(c) as health:
        before, start = tree_cpu(c.api.pid), time.monotonic()
        resp = upload(c.http, archive)
        wall, cpu = time.monotonic() - start, tree_cpu(c.api.pid) - before
    if resp.status_code == 201:
        job_id = resp.json()["id"]
        c.http.delete(f"/v1/jobs/{job_id}")  # cancelled (no workers)
        c.http.delete(f"/v1/jobs/{job_id}")  # deleted
    return {"case": name, "upload_bytes": len(archive), "status": resp.status_code, "wall_s": round(wall, 3),
            "api_cpu_s": round(cpu, 3), **health.summary(), "detail": _detail(resp)}


def concurrent(c: Cluster, archives: list[bytes]) -> dict:
    """The uploads sent at once while /healthz is asked every HEALTH_EVERY seconds."""
    statuses: list[int] = []

    def send(archive: bytes) -> None:
        with httpx.Client(base_url=str(c.http.base_url)) as http:
            statuses.append(upload(http, archive).status_code)

    with HealthPoller(c) as health:
        before, start = tree_cpu(c.api.pid), time.monotonic()
        senders = [threading.Thread(target=send, args=(a,)) for a in archives]
        for t in senders:
            t.start()
        for t in senders:
            t.join()
        wall, cpu = time.monotonic() - start, tree_cpu(c.api.pid) - before
    for job in c.http.get("/v1/jobs").json():
        c.http.delete(f"/v1/jobs/{job['id']}")
        c.http.delete(f"/v1/jobs/{job['id']}")
    return {"uploads": len(archives), "statuses": sorted(statuses), "wall_s": round(wall, 3),
            "api_cpu_s": round(cpu, 3), **health.summary()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--concurrent", type=int, default=10)
    parser.add_argument("--rounds", type=int, default=1, help="times each case is sent (the figures are per upload)")
    args = parser.parse_args()
    archives = {name: make() for name, make in CASES.items()}
    for name, archive in archives.items():
        assert len(archive) <= LIMIT_BYTES, (name, len(archive))
    with tempfile.TemporaryDirectory(prefix="upload-cost-") as tmp:
        c = Cluster(Path(tmp), workers=0)
        try:
            upload(c.http, archives["deep nest"])  # the loaders' forkserver starts on the first load
            rows = [one(c, name, archive) for _ in range(args.rounds) for name, archive in archives.items()]
            names = list(archives)
            together = concurrent(c, [archives[names[i % len(names)]] for i in range(args.concurrent)])
        finally:
            c.close()
    print(f"{'case':26} {'bytes':>8} {'status':>6} {'wall s':>7} {'API CPU s':>9} {'healthz max ms':>14}  answer")
    for r in rows:
        print(f"{r['case']:26} {r['upload_bytes']:8d} {r['status']:6d} {r['wall_s']:7.2f} {r['api_cpu_s']:9.2f} "
              f"{r['healthz_max_ms']:14.1f}  {r['detail'][:70]}")
    print(f"\n{together['uploads']} at once: statuses {together['statuses']}, {together['wall_s']:.1f} s wall, "
          f"{together['api_cpu_s']:.1f} s API CPU; /healthz ({together['healthz_n']} asks) p50 "
          f"{together['healthz_p50_ms']} ms, p99 {together['healthz_p99_ms']} ms, max {together['healthz_max_ms']} ms")
    path = write_json("upload_cost", {"cases": rows, "concurrent": together, "limit_bytes": LIMIT_BYTES,
                                      "cpu_count": psutil.cpu_count()})
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
