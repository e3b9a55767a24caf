"""Security and integrity of the service from outside (issue 10, items 5-9, 11, 13): a
scene name is never a path, the embedded Redis wants a password and runs no code for
whoever reaches it, the bearer check follows RFC 7235, bad input gets 422, the OpenAPI
document and /docs work offline, `photonfarm serve` takes every child with it, and
repeated reads are served from memory; the safe defaults (issue 51, part 6): no bind
beyond loopback without a token, no secret on a command line, archive members checked
before they are read, the image's user and compose's port. Real Redis, real workers, real
HTTP."""

from __future__ import annotations

import gzip
import json
import os
import re
import signal
import stat
import subprocess
import sys
import tarfile
import time
import zlib
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
import redis
import yaml
from rq import Callback, Queue
from rq.serializers import JSONSerializer

from api_tests import tripwire
from api_tests.cluster import Cluster, finished
from api_tests.helpers import CHROMIUM, CHROMIUM_FLAGS, assert_exact, zip_bomb
from service.redis_server import AOF_DIR, AOF_FILE, DISABLED_COMMANDS, PASSWORD_FILE, EmbeddedRedis, free_port
from worker.scheduler import QUEUE_NAMES

REPO = Path(__file__).resolve().parent.parent
TOKEN = "s3cret-token"
P = 1 << 12


@pytest.fixture(scope="module")
def secured(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Cluster]:
    c = Cluster(tmp_path_factory.mktemp("secured"), workers=2, token=TOKEN)
    yield c
    c.close()


def _furnace(c: Cluster) -> dict:
    return c.http.get("/v1/scenes/furnace").json()


def _names_field(resp: httpx.Response, *loc: str | int) -> None:
    assert resp.status_code == 422, (resp.status_code, resp.text)
    assert any(tuple(e["loc"][:len(loc)]) == loc for e in resp.json()["detail"]), resp.text


# ------------------------------------------------------------------------ 5, 8: scene names
def test_scene_name_is_never_a_path(secured: Cluster, tmp_path: Path) -> None:
    elsewhere = tmp_path / "elsewhere"
    (tmp_path / "elsewhere.json").write_text(json.dumps(_furnace(secured)))  # a valid scene outside scenes/
    for name in (str(elsewhere), "../scenes/furnace", "furnace.json", "Furnace", "-furnace", "", "a" * 300,
                 "no-such-scene"):
        _names_field(secured.http.post("/v1/jobs", json={"scene_name": name}), "body", "scene_name")
    for name in ("no-such-scene", "..%2F..%2Fetc%2Fpasswd", "..", "%2Fetc%2Fpasswd"):
        assert secured.http.get(f"/v1/scenes/{name}").status_code in (404, 422), name
    assert secured.http.get("/v1/scenes/no-such-scene").status_code == 404
    _names_field(secured.http.get("/v1/scenes/" + "a" * 300), "path", "name")
    job = secured.submit(scene_name="furnace", settings={"max_passes": 3, "photons_per_pass": P})
    assert_exact(secured, job["id"], 3, P)  # a bundled name still renders


def test_mesh_file_names_the_file_system_refuses_are_422(secured: Cluster) -> None:
    scene = _furnace(secured)
    for obj in ("m" * 300 + ".obj", "x\x00.obj", "\u00e9" * 200 + ".obj"):  # the last: 200 chars, 400 bytes
        scene["shapes"] = [scene["shapes"][0], {"type": "mesh", "file": obj, "material": "wall"}]
        _names_field(secured.http.post("/v1/jobs", json={"scene": scene}), "body", "scene", "shapes", 1, "file")


def test_undecodable_and_deeply_nested_bodies_are_422(secured: Cluster) -> None:
    headers = {"content-type": "application/json"}
    for body in (b"\xff\xfe{\x00", b'{"scene_name": "\xc3\x28"}', b"[" * 1500 + b"]" * 1500,
                 b'{"scene": ' + b'{"a": ' * 1200 + b"1" + b"}" * 1201):
        resp = secured.http.post("/v1/jobs", content=body, headers=headers)
        _names_field(resp, "body")


# ------------------------------------------------------------------------------ 7: bearer
def test_bearer_scheme_is_case_insensitive_and_token_exact(secured: Cluster) -> None:
    url = f"{secured.http.base_url}/v1/jobs"
    for header in (f"Bearer {TOKEN}", f"bearer {TOKEN}", f"BEARER {TOKEN}", f"bEaReR  {TOKEN}"):
        assert httpx.get(url, headers={"Authorization": header}).status_code == 200, header
    for header in (None, f"Bearer {TOKEN[:-1]}", f"Bearer {TOKEN}x", f"Basic {TOKEN}", TOKEN, "Bearer",
                   f"Bearer {TOKEN.upper()}"):
        resp = httpx.get(url, headers={"Authorization": header} if header else {})
        assert resp.status_code == 401 and resp.headers["www-authenticate"] == "Bearer", header
    assert httpx.get(f"{secured.http.base_url}/healthz").status_code == 200


# ---------------------------------------------------------------------------- 9: OpenAPI
def test_openapi_declares_errors_and_the_bearer_scheme(secured: Cluster) -> None:
    spec = httpx.get(f"{secured.http.base_url}/openapi.json").json()  # no token: it holds no data
    schemes = spec["components"]["securitySchemes"]
    assert [s["scheme"] for s in schemes.values()] == ["bearer"]
    expected = {("post", "/v1/jobs"): {"401", "413", "422"}, ("get", "/v1/jobs/{job_id}"): {"401", "404"},
                ("delete", "/v1/jobs/{job_id}"): {"204", "401", "404"},
                ("get", "/v1/jobs/{job_id}/error"): {"401", "404", "409", "422"},
                ("get", "/v1/jobs/{job_id}/image"): {"401", "404", "422"},
                ("get", "/v1/scenes/{name}"): {"401", "404", "422"}, ("get", "/metrics"): {"401"}}
    for (method, path), codes in expected.items():
        op = spec["paths"][path][method]
        assert codes <= set(op["responses"]), (path, sorted(op["responses"]))
        assert op["security"] == [{name: []} for name in schemes], path
    assert "security" not in spec["paths"]["/healthz"]["get"]


def test_docs_load_from_the_service_alone(secured: Cluster) -> None:
    base = str(secured.http.base_url)
    for page in ("/docs", "/redoc"):
        html = httpx.get(f"{base}{page}").text
        assert not re.search(r"https?://", html), f"{page} names an outside host"
        assets = re.findall(r'(?:src|href)="([^"]+)"', html)
        assert any(a.endswith(".js") for a in assets), assets
        for asset in assets:
            resp = httpx.get(base + asset)
            assert resp.status_code == 200 and len(resp.content) > 1000, asset
    assert any(a.endswith(".css") for a in re.findall(r'href="([^"]+)"', httpx.get(f"{base}/docs").text))

    if CHROMIUM is None:
        pytest.skip("Debian's chromium is not installed here (.ci/run installs it): the browser half is skipped")
    from playwright.sync_api import sync_playwright

    requested: list[str] = []
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_FLAGS)
        page = browser.new_page()
        page.on("request", lambda req: requested.append(req.url))
        page.goto(f"{base}/docs")
        page.wait_for_selector("button.authorize", timeout=20_000)  # the bearer scheme's button
        page.wait_for_selector('[data-path="/v1/jobs/{job_id}/image"]', timeout=20_000)  # operations rendered
        browser.close()
    hosts = {httpx.URL(url).host for url in requested if url.startswith(("http:", "https:"))}
    assert hosts == {"127.0.0.1"}, requested


# ------------------------------------------------------------------------ 6: Redis security
def test_embedded_redis_wants_its_password_and_runs_no_code(secured: Cluster, tmp_path: Path) -> None:
    r = secured.redis_client
    anonymous = redis.Redis(host=secured.redis.bind, port=secured.redis.port)
    with pytest.raises(redis.AuthenticationError):
        anonymous.ping()
    with pytest.raises(redis.AuthenticationError):
        redis.Redis(host=secured.redis.bind, port=secured.redis.port, password="guess").ping()
    for command in (["CONFIG", "GET", "dir"], ["DEBUG", "SLEEP", "0"], ["MODULE", "LIST"], ["SLAVEOF", "NO", "ONE"]):
        with pytest.raises(redis.ResponseError, match="unknown command"):
            r.execute_command(*command)

    # job arguments travel as JSON (read while the job's batches are queued or running)
    job = secured.submit(scene_name="furnace", settings={"max_passes": 40, "photons_per_pass": P})
    payloads: list[bytes] = []
    while not payloads and not finished(secured.job(job["id"])):
        payloads = [p for p in (r.hget(k, "data") for k in r.scan_iter("rq:job:pf-*")) if p]
        time.sleep(0.05)
    assert payloads and all(json.loads(zlib.decompress(p))[0] == "worker.tasks.run_batch" for p in payloads)
    assert_exact(secured, job["id"], 40, P)

    # private files: directories 0700, password and the append-only file's parts 0600, owner only
    data = secured.redis.data_dir
    assert all(stat.S_IMODE(d.stat().st_mode) == 0o700 for d in (data, data / AOF_DIR))
    files = [f for d in (data, data / AOF_DIR) for f in d.iterdir() if f.is_file()]
    assert {PASSWORD_FILE, f"{AOF_FILE}.manifest"} <= {f.name for f in files}
    assert all(stat.S_IMODE(f.stat().st_mode) == 0o600 for f in files), [(f.name, oct(f.stat().st_mode)) for f in files]

    # no command line shows the password (any local user reads /proc/PID/cmdline)
    password = secured.redis.password
    for proc in [*secured.workers, secured.api, secured.redis.proc]:
        assert password.encode() not in Path(f"/proc/{proc.pid}/cmdline").read_bytes()

    # a pickle that would run code, and a JSON job naming another function: neither runs
    marker, other = tmp_path / "pickle-ran", tmp_path / "json-ran"

    class Payload:
        def __reduce__(self):  # what an attacker would put in the queue
            return (os.mkdir, (str(marker),))

    queue = QUEUE_NAMES[0]
    pickled = Queue(queue, connection=r).enqueue_call("worker.tasks.run_batch", args=(Payload(),))
    named = Queue(queue, connection=r, serializer=JSONSerializer).enqueue_call("os.mkdir", args=(str(other),))
    deadline = time.time() + 30
    while time.time() < deadline and {r.hget(f"rq:job:{j.id}", "status") for j in (pickled, named)} != {b"failed"}:
        time.sleep(0.2)
    assert {r.hget(f"rq:job:{j.id}", "status") for j in (pickled, named)} == {b"failed"}
    assert not marker.exists() and not other.exists()
    assert all(proc.poll() is None for proc in secured.workers)  # the workers survived both
    job = secured.submit(scene_name="furnace", settings={"max_passes": 2, "photons_per_pass": P})
    assert_exact(secured, job["id"], 2, P)


def test_a_worker_resolves_no_callable_a_queued_job_names(tmp_path: Path) -> None:
    """Whoever reaches Redis may write any RQ job: a function, success, failure and stopped
    callbacks, a dependency. A worker imports and runs none of them but the render task: a
    job naming anything else, as its function or as any callback, is failed unrun, and the
    tripwire module (a file when imported or called) is never even imported."""
    sprung = tmp_path / "tripwire"
    sprung.mkdir()
    c = Cluster(tmp_path / "cluster", workers=1, env={tripwire.DIR_ENV: str(sprung)})
    try:
        r = c.redis_client
        queue = Queue(QUEUE_NAMES[0], connection=r, serializer=JSONSerializer)
        trap, task = "api_tests.tripwire.spring", "worker.tasks.run_batch"
        skipped = ("no-such-job", 0, 1)  # a batch of no job: the task returns "skipped", unrendered
        refused = [
            queue.enqueue_call(trap, args=(1,)),
            queue.enqueue_call(trap, args=(1,), on_failure=Callback(trap)),
            queue.enqueue_call(task, args=skipped, on_success=Callback(trap)),
            queue.enqueue_call(task, args=("no-such-job",), on_failure=Callback(trap)),  # the task's TypeError
            queue.enqueue_call(task, args=skipped, on_stopped=Callback(trap)),
            queue.enqueue_call("builtins.print", args=("ran",), on_success=Callback("builtins.print")),
        ]
        parent = queue.enqueue_call(task, args=skipped)
        refused.append(queue.enqueue_call(task, args=skipped, depends_on=parent, on_success=Callback(trap)))
        deadline = time.time() + 60
        statuses: list[bytes | None] = []
        while time.time() < deadline:
            statuses = [r.hget(f"rq:job:{j.id}", "status") for j in refused]
            if all(s == b"failed" for s in statuses):
                break
            time.sleep(0.2)
        assert statuses == [b"failed"] * len(refused), statuses
        assert r.hget(f"rq:job:{parent.id}", "status") == b"finished"  # the plain task still runs
        assert sorted(p.name for p in sprung.iterdir()) == []  # nothing imported, nothing called
        assert all(proc.poll() is None for proc in c.workers)
        job = c.submit(scene_name="furnace", settings={"max_passes": 2, "photons_per_pass": P})
        assert_exact(c, job["id"], 2, P)
    finally:
        c.close()


def test_password_is_kept_across_restarts_of_a_data_dir(tmp_path: Path) -> None:
    first = EmbeddedRedis(tmp_path / "redis").start(supervise=False)
    try:
        redis.Redis.from_url(first.url).set("kept", "yes")
        assert set(DISABLED_COMMANDS) >= {"CONFIG", "DEBUG", "MODULE"}
    finally:
        first.stop()
    again = EmbeddedRedis(tmp_path / "redis", port=free_port()).start(supervise=False)
    try:
        assert again.password == first.password
        assert redis.Redis.from_url(again.url).get("kept") == b"yes"
        other = EmbeddedRedis(tmp_path / "other")
        assert other.password != first.password  # each data directory its own
    finally:
        again.stop()


# -------------------------------------------------------------------- 11: serve and its children
def _session_members(sid: int) -> set[int]:
    """Live (non-zombie) processes of a session."""
    out = set()
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[3]) == sid and fields[0] != "Z":  # fields: state, ppid, pgrp, session
            out.add(int(entry.name))
    return out


def _serve_mid_batch(data_dir: Path) -> tuple[subprocess.Popen, httpx.Client, str]:
    """`photonfarm serve` with its embedded Redis and 2 workers, a job rendering."""
    port = free_port()
    env = {k: v for k, v in os.environ.items() if k not in ("REDIS_URL", "PHOTONFARM_TOKEN")}
    env["POCL_MAX_PTHREAD_COUNT"] = "1"
    log = open(data_dir / "serve.log", "ab")
    proc = subprocess.Popen([sys.executable, "-m", "service.cli", "serve", "--port", str(port), "--workers", "2",
                             "--data-dir", str(data_dir)], env=env, stdout=log, stderr=subprocess.STDOUT,
                            start_new_session=True)
    http = httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=30)
    deadline = time.time() + 60
    while time.time() < deadline:
        try:
            if http.get("/healthz").status_code == 200:
                break
        except httpx.TransportError:
            time.sleep(0.2)
    job = http.post("/v1/jobs", json={"scene_name": "cornell-caustics", "settings": {
        "max_passes": 100_000, "photons_per_pass": 1 << 14, "resolution": [64, 64]}}).json()
    while time.time() < deadline and http.get(f"/v1/jobs/{job['id']}").json()["passes"] < 2:
        time.sleep(0.1)
    assert http.get(f"/v1/jobs/{job['id']}").json()["status"] == "running"  # batches keep coming
    return proc, http, job["id"]


def _wait_empty(sid: int, seconds: float) -> set[int]:
    deadline = time.time() + seconds
    while time.time() < deadline and _session_members(sid):
        time.sleep(0.1)
    return _session_members(sid)


@pytest.mark.parametrize("how", ["sigterm", "sigkill-group", "sigkill-serve"])
def test_serve_takes_every_child_with_it(how: str, tmp_path: Path) -> None:
    proc, http, _ = _serve_mid_batch(tmp_path)
    children = _session_members(proc.pid) - {proc.pid}
    try:
        assert len(children) >= 4, children  # redis-server, a reducer and two workers
        start = time.time()
        if how == "sigterm":
            proc.send_signal(signal.SIGTERM)  # what docker stop and systemd send
            assert proc.wait(timeout=30) == 0
        elif how == "sigkill-group":
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(timeout=10)
        else:  # serve alone, no cleanup: the kernel's parent-death signal must do it
            proc.kill()
            proc.wait(timeout=10)
        left = _wait_empty(proc.pid, 15.0)
        assert not left, f"{how}: still running {time.time() - start:.1f} s later: {left}"
    finally:
        http.close()
        for pid in _session_members(proc.pid):
            os.kill(pid, signal.SIGKILL)


# --------------------------------------------------------------- 13: repeated reads from memory
def test_repeated_image_reads_are_served_from_memory(secured: Cluster) -> None:
    job = secured.submit(scene_name="furnace", settings={"max_passes": 2, "photons_per_pass": P,
                                                         "resolution": [512, 512]})
    assert_exact(secured, job["id"], 2, P)
    url = job["links"]["image_png"]
    t0 = time.perf_counter()
    first = secured.http.get(url)  # reads the job's state (512 x 512 pixels) and encodes it
    miss = time.perf_counter() - t0
    hits = []
    for _ in range(9):
        t0 = time.perf_counter()
        again = secured.http.get(url)
        hits.append(time.perf_counter() - t0)
        assert again.content == first.content and again.headers["x-passes"] == "2"
    assert sorted(hits)[4] < miss / 4, (miss, hits)  # the median repeat costs a fraction of an encode


def test_cached_images_follow_every_merge(secured: Cluster) -> None:
    job = secured.submit(scene_name="furnace", settings={"max_passes": 60, "photons_per_pass": P})
    seen: dict[str, set[bytes]] = {}  # X-Passes -> the images served with it
    deadline = time.time() + 120
    while time.time() < deadline:
        done = finished(secured.job(job["id"]))
        resp = secured.http.get(job["links"]["image_png"])
        seen.setdefault(resp.headers["x-passes"], set()).add(resp.content)
        if done:
            break
    assert "60" in seen and len(seen) > 1, sorted(seen)
    assert all(len(images) == 1 for images in seen.values())  # one image per merge count
    assert len(set().union(*seen.values())) == len(seen)  # a new merge, a new image
    assert_exact(secured, job["id"], 60, P)


def test_metrics_scrapes_do_not_each_read_every_job(secured: Cluster) -> None:
    r = secured.redis_client

    def hgetalls() -> int:
        return r.info("commandstats").get("cmdstat_hgetall", {}).get("calls", 0)

    for _ in range(3):  # a few finished jobs for a scrape to read
        job = secured.submit(scene_name="furnace", settings={"max_passes": 1, "photons_per_pass": P})
        secured.wait(job["id"], finished)
    time.sleep(1.5)
    before = hgetalls()
    assert secured.http.get("/metrics").status_code == 200
    one = hgetalls() - before
    assert one >= len(secured.http.get("/v1/jobs").json())  # a scrape that reads does read every job
    before = hgetalls()
    texts = {secured.http.get("/metrics").text for _ in range(10)}
    burst = hgetalls() - before
    assert burst < 5 * one, (one, burst)  # ten scrapes within a second: not ten reads of every job
    assert all("photonfarm_jobs" in t for t in texts)


# ------------------------------------------------------------------ issue 51, 6: safe defaults
def _serve(args: list[str], data_dir: Path, env: dict[str, str]) -> subprocess.Popen:
    """`photonfarm serve` (the real CLI) in a session of its own, its output in data_dir/serve.log."""
    clean = {k: v for k, v in os.environ.items() if not k.startswith(("REDIS_", "PHOTONFARM_"))}
    log = open(data_dir / "serve.log", "ab")
    return subprocess.Popen([sys.executable, "-m", "service.cli", "serve", "--data-dir", str(data_dir / "data"),
                             *args], env={**clean, "POCL_MAX_PTHREAD_COUNT": "1", **env}, stdout=log,
                            stderr=subprocess.STDOUT, start_new_session=True)


def _stop(proc: subprocess.Popen) -> None:
    proc.send_signal(signal.SIGTERM)
    try:
        proc.wait(timeout=30)
    finally:
        for pid in _session_members(proc.pid):
            os.kill(pid, signal.SIGKILL)


def _healthy(url: str, proc: subprocess.Popen, seconds: float = 60.0) -> None:
    deadline = time.time() + seconds
    while time.time() < deadline and proc.poll() is None:
        try:
            if httpx.get(f"{url}/healthz", timeout=2).status_code == 200:
                return
        except httpx.TransportError:
            time.sleep(0.2)
    raise AssertionError(f"serve did not come up (exit {proc.poll()})")


@pytest.mark.parametrize("host", ["0.0.0.0", "::", "192.0.2.1", "example.com", ""])
def test_serve_binds_beyond_loopback_only_with_a_token(host: str, tmp_path: Path) -> None:
    proc = _serve(["--host", host, "--port", str(free_port())], tmp_path, {})
    assert proc.wait(timeout=60) == 2
    out = (tmp_path / "serve.log").read_text().strip()
    assert out == (f"photonfarm: serve --host {host} is reachable beyond this machine: set PHOTONFARM_TOKEN or "
                   "PHOTONFARM_TOKEN_FILE first (docs/farm.md, Security model)"), out
    assert not (tmp_path / "data").exists()  # refused before anything started: no Redis, no data


def test_loopback_names_only_this_machine() -> None:
    from service.cli import loopback

    assert all(loopback(h) for h in ("127.0.0.1", "127.8.9.10", "::1", "localhost"))
    assert not any(loopback(h) for h in ("0.0.0.0", "::", "", "10.0.0.1", "128.0.0.1", "localhost.example.com",
                                         "::ffff:127.0.0.1x", "fe80::1"))


def test_serve_with_a_token_file_binds_everywhere_wants_the_token_and_shows_no_secret(tmp_path: Path) -> None:
    """0.0.0.0 with the token in a file: data routes want it; no process serve starts (the
    embedded Redis, the reducer, the workers) carries the Redis password or the token on its command line."""
    token_file = tmp_path / "token"
    token_file.write_text(TOKEN + "\n")
    port = free_port("0.0.0.0")
    proc = _serve(["--host", "0.0.0.0", "--port", str(port), "--workers", "2"], tmp_path,
                  {"PHOTONFARM_TOKEN_FILE": str(token_file)})
    try:
        url = f"http://127.0.0.1:{port}"
        _healthy(url, proc)
        assert httpx.get(f"{url}/v1/jobs").status_code == 401
        assert httpx.get(f"{url}/v1/jobs", headers={"Authorization": f"Bearer {TOKEN}x"}).status_code == 401
        assert httpx.get(f"{url}/v1/jobs", headers={"Authorization": f"Bearer {TOKEN}"}).status_code == 200
        password = (tmp_path / "data" / "redis" / PASSWORD_FILE).read_text().strip()
        members = _session_members(proc.pid)
        lines = {pid: Path(f"/proc/{pid}/cmdline").read_bytes() for pid in members}
        assert len(lines) >= 5, lines  # serve, redis-server, a reducer and two workers
        assert any(b"valkey-server" in c or b"redis-server" in c for c in lines.values()), lines
        for pid, cmdline in lines.items():
            assert password.encode() not in cmdline and TOKEN.encode() not in cmdline, (pid, cmdline)
    finally:
        _stop(proc)


def _tar_gz(*blocks: bytes) -> bytes:
    """A .tar.gz of raw tar blocks, as a hostile client may write them (no end marker needed:
    the upload is refused at the first header that asks for too much)."""
    return gzip.compress(b"".join(blocks), compresslevel=9)


def _pax_header(name: str, records: dict[str, str]) -> bytes:
    """A pax extended header and its records, for the member `name` that follows."""
    info = tarfile.TarInfo(name)
    info.pax_headers = records
    return info.tobuf(tarfile.PAX_FORMAT)


def _peak_rss(pid: int) -> int:
    """A process's peak resident memory in bytes (VmHWM)."""
    line = next(s for s in Path(f"/proc/{pid}/status").read_text().splitlines() if s.startswith("VmHWM:"))
    return int(line.split()[1]) * 1024


@pytest.fixture(scope="module")
def uploads(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Cluster]:
    """An API of its own (its peak memory starts low), one worker."""
    c = Cluster(tmp_path_factory.mktemp("uploads"), workers=1)
    yield c
    c.close()


def _post_archive(c: Cluster, name: str, data: bytes) -> httpx.Response:
    return c.http.post("/v1/jobs/upload", files=[("archive", (name, data))],
                       data={"scene": "s.json", "settings": json.dumps({"max_passes": 1})})


def _serves_on(c: Cluster) -> None:
    assert c.api is not None and c.api.poll() is None
    job = c.submit(scene_name="furnace", settings={"max_passes": 2, "photons_per_pass": P})
    assert_exact(c, job["id"], 2, P)


def test_a_tar_member_declaring_more_than_the_limit_is_413_before_it_is_read(uploads: Cluster) -> None:
    huge = tarfile.TarInfo("meshes/huge.ply")
    huge.size = 64 * 2**30  # 64 GiB declared; none of it sent
    resp = _post_archive(uploads, "huge.tar.gz", _tar_gz(huge.tobuf(tarfile.GNU_FORMAT)))
    detail = resp.json()["detail"]
    assert resp.status_code == 413 and "'meshes/huge.ply'" in detail and f"{huge.size}" in detail, resp.text
    _serves_on(uploads)


def test_a_lying_tar_header_is_413_naming_its_member(uploads: Cluster) -> None:
    """The member's own header says 0 bytes; the pax header before it says 5 GiB (a pax size
    overrides the header's): the size checked is the one tarfile would read."""
    liar = tarfile.TarInfo("liar.ply")  # size 0
    archive = _tar_gz(_pax_header("liar.ply", {"size": str(5 * 2**30)}), liar.tobuf(tarfile.USTAR_FORMAT))
    resp = _post_archive(uploads, "liar.tgz", archive)
    assert resp.status_code == 413 and "'liar.ply'" in resp.json()["detail"], resp.text
    _serves_on(uploads)


def test_a_tar_header_bomb_is_413_without_reading_it(uploads: Cluster) -> None:
    """A pax header whose content is 100 MB of zeros (100 KB compressed): tarfile reads such
    a content whole, so it is refused from its declared size, before the read; the API's
    peak memory shows it was not read."""
    content = 100 * 10**6
    header = tarfile.TarInfo("././@PaxHeader")
    header.type, header.size = tarfile.XHDTYPE, content
    archive = _tar_gz(header.tobuf(tarfile.USTAR_FORMAT), bytes(content))
    assert len(archive) < 200_000
    assert uploads.api is not None
    before = _peak_rss(uploads.api.pid)
    resp = _post_archive(uploads, "bomb.tar.gz", archive)
    grown = _peak_rss(uploads.api.pid) - before
    assert grown < content // 4, (before, grown)
    assert resp.status_code == 413 and "'././@PaxHeader'" in resp.json()["detail"], resp.text
    _serves_on(uploads)


def test_a_zip_member_declaring_more_than_the_limit_is_413_naming_it(uploads: Cluster) -> None:
    bomb = zip_bomb()  # zeros.ply declares (truly) more than the limit
    resp = _post_archive(uploads, "bomb.zip", bomb)
    assert resp.status_code == 413 and "'zeros.ply' declares" in resp.json()["detail"], resp.text
    _serves_on(uploads)


# ----------------------------------------------------------------- the deployment files' defaults
def test_the_image_runs_as_a_user_of_its_own() -> None:
    lines = [line.split() for line in (REPO / "Dockerfile").read_text().splitlines() if line.strip()]
    users = [words[1] for words in lines if words[0] == "USER"]
    assert users and users[-1] not in ("root", "0") and not users[-1].startswith(("root:", "0:")), users
    last_user = max(i for i, words in enumerate(lines) if words[0] == "USER")
    assert all(words[0] not in ("RUN", "COPY", "ADD") for words in lines[last_user:])  # nothing after it as root


def test_compose_publishes_the_api_on_loopback_and_puts_no_password_on_a_command_line() -> None:
    services = yaml.safe_load((REPO / "docker-compose.yml").read_text())["services"]
    for name, service in services.items():
        for port in service.get("ports", []):
            assert str(port).startswith("127.0.0.1:"), (name, port)
    assert "ports" not in services["redis"]
    assert services["api"]["environment"]["PHOTONFARM_TOKEN"].startswith("${PHOTONFARM_TOKEN:?")  # required
    # A secret's value interpolated by compose (`${REDIS_PASSWORD}`, `$REDIS_PASSWORD`) would be on
    # the argv; `$$REDIS_PASSWORD` is the container shell's reference, read from its environment.
    interpolated = re.compile(r"\$\{?(?:REDIS_PASSWORD|PHOTONFARM_TOKEN)")
    for name, service in services.items():
        argv = [str(a) for a in [*service.get("entrypoint", []), *service.get("command", [])]]
        assert "--requirepass" not in argv and not any(interpolated.search(a.replace("$$", "")) for a in argv), name
