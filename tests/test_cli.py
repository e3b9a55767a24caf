"""The first minutes of a new user with `photonfarm render` (issue 11): the output path is
checked before rendering, Ctrl-C keeps the image so far, logs get no progress redraws,
and an EXR carries what made it."""

from __future__ import annotations

import json
import signal
import socket
import subprocess
import time
from pathlib import Path

from tests.helpers import PHOTONFARM, SMALL, render_cli
from worker.image_io import read_channels, read_image, read_metadata
from worker.queue_worker import BURST_PATIENCE_SECONDS


def test_missing_output_folders_are_created(tmp_path: Path) -> None:
    out = tmp_path / "out" / "deeper" / "cc.png"
    proc = render_cli("furnace", "--passes", "2", *SMALL, "--out", str(out))
    assert proc.returncode == 0, proc.stderr
    assert read_image(out).shape == (16, 16, 3)


def test_an_unwritable_output_is_one_line_before_rendering(tmp_path: Path) -> None:
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    t0 = time.perf_counter()
    proc = render_cli("furnace", "--passes", "100000", *SMALL, "--out", str(blocker / "x.png"))
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1 and "cannot write" in proc.stderr, proc.stderr
    assert time.perf_counter() - t0 < 30  # it did not render 100000 passes first


def test_a_scene_file_of_another_kind_is_named_as_such(tmp_path: Path) -> None:
    """An existing file that is not .json or .xml is not looked up as a bundled scene's name."""
    other = tmp_path / "scene.txt"
    other.write_text("{}")
    proc = render_cli(str(other), "--passes", "1", *SMALL, "--out", str(tmp_path / "x.png"))
    assert proc.returncode == 2 and len(proc.stderr.strip().splitlines()) == 1, proc.stderr
    assert ".json" in proc.stderr and "bundled" not in proc.stderr, proc.stderr


def test_ctrl_c_writes_the_image_so_far(tmp_path: Path) -> None:
    out = tmp_path / "so-far.exr"
    proc = subprocess.Popen([str(PHOTONFARM), "render", "furnace", "--seconds", "120", *SMALL, "--out", str(out)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    time.sleep(8.0)  # set-up and some passes
    proc.send_signal(signal.SIGINT)
    stdout, stderr = proc.communicate(timeout=60)
    assert "Traceback" not in stderr, stderr
    if "before the first pass" in stderr:  # a very slow machine: still a clean one-line answer
        assert proc.returncode == 130 and not out.exists()
        return
    assert proc.returncode == 130 and "interrupted" in stdout, (stdout, stderr)
    passes = int(read_metadata(out)["passes"])
    assert passes >= 1 and read_image(out)[..., :3].mean() > 0.0


def test_no_progress_redraws_when_stderr_is_not_a_terminal(tmp_path: Path) -> None:
    proc = render_cli("furnace", "--passes", "3", *SMALL, "--out", str(tmp_path / "x.png"))
    assert proc.returncode == 0 and "\r" not in proc.stderr, repr(proc.stderr)


def test_exr_carries_metadata_and_error_layers(tmp_path: Path) -> None:
    out = tmp_path / "x.exr"
    proc = render_cli("furnace", "--passes", "4", *SMALL, "--seed", "5", "--out", str(out))
    assert proc.returncode == 0, proc.stderr
    meta = read_metadata(out)
    assert meta["passes"] == "4" and meta["photons"] == str(4 * 4096) and meta["seed"] == "5"
    assert meta["method"] == "sppm" and json.loads(meta["settings"])["photons_per_pass"] == 4096
    assert 0.0 < float(meta["error_estimate"]) < 10.0 and meta["confidence"] == "0.9"
    channels = read_channels(out)
    assert {"R", "G", "B", "error.bias", "error.noise", "error.bound", "error.relative"} <= set(channels)
    assert (channels["error.bound"] >= channels["error.noise"] - 1e-6).all()
    assert read_image(out)[..., :3].mean() > 0.0  # R, G, B still come first for plain readers


def test_submit_eta_from_the_error_slope() -> None:
    from service.client import eta_seconds

    # error = 10 * seconds^-0.5: it meets 0.5 at 400 s
    history = [{"seconds": float(t), "error": 10.0 * t ** -0.5} for t in (4, 9, 16, 25, 36, 49, 64)]
    job = {"settings": {"error_threshold": 0.5, "max_seconds": 1000.0}, "error_history": history,
           "elapsed_seconds": 64.0, "passes": 7}
    assert abs(eta_seconds(job) - (400.0 - 64.0)) < 1.0
    job["settings"] = {"max_seconds": 100.0}
    assert eta_seconds(job) == 36.0


def test_convert_and_render_a_mitsuba_scene_from_anywhere(tmp_path: Path) -> None:
    out = tmp_path / "conv" / "obj-mesh.json"
    proc = subprocess.run([str(PHOTONFARM), "convert", "scenes/mitsuba/obj-mesh.xml", "--out", str(out)],
                          capture_output=True, text=True, timeout=120, cwd=Path(__file__).resolve().parent.parent)
    assert proc.returncode == 0, proc.stderr
    from worker.scene import parse_scene

    assert parse_scene(json.loads(out.read_text())).camera  # our JSON, meshes inlined
    image = tmp_path / "xml.png"
    proc = render_cli(str(Path(__file__).resolve().parent.parent / "scenes" / "mitsuba" / "ply-mesh.xml"),
                      "--passes", "1", *SMALL, "--out", str(image))
    assert proc.returncode == 0 and read_image(image).shape == (16, 16, 3), proc.stderr
    bad = tmp_path / "bad.xml"
    bad.write_text('<scene version="3.0.0">\n  <bsdf type="hair"/>\n</scene>\n')
    proc = subprocess.run([str(PHOTONFARM), "convert", str(bad)], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and "line 2" in proc.stderr and len(proc.stderr.strip().splitlines()) == 1, proc.stderr


def test_mitsuba_notes_and_refusals_are_one_line_each(tmp_path: Path) -> None:
    """What a Mitsuba scene holds that changes nothing is printed as notes, one line each,
    by convert and by render; what cannot be honoured is one line naming plugin and line."""
    repo = Path(__file__).resolve().parent.parent
    scene = repo / "scenes" / "mitsuba" / "spectral-box.xml"
    proc = subprocess.run([str(PHOTONFARM), "convert", str(scene), "--out", str(tmp_path / "box.json")],
                          capture_output=True, text=True, timeout=120)
    notes = proc.stderr.strip().splitlines()
    assert proc.returncode == 0 and len(notes) == 8, proc.stderr
    assert all(line.startswith("photonfarm: ignored: spectral-box.xml line ") for line in notes), notes
    proc = render_cli(str(scene), "--passes", "1", *SMALL, "--out", str(tmp_path / "box.png"))
    assert proc.returncode == 0 and sum("focus_distance" in line for line in proc.stderr.splitlines()) == 1, proc.stderr
    fog = tmp_path / "fog.xml"
    fog.write_text('<scene version="3.0.0">\n  <medium type="homogeneous" id="fog"/>\n</scene>\n')
    proc = subprocess.run([str(PHOTONFARM), "convert", str(fog)], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and proc.stderr.strip() == ('photonfarm: bad scene: fog.xml: line 2: '
                                                             '<medium type="homogeneous">: participating media are '
                                                             'not supported'), proc.stderr


def test_service_flags_are_checked_before_anything_starts(tmp_path: Path) -> None:
    """A Redis URL of another scheme or with a password (the command line is readable by any
    local user), or a negative worker or reducer count: one line, exit 2 (the URL was
    a traceback from the worker's Redis client; -1 workers started the API with none)."""
    for args in (["worker", "--redis-url", "http://:secret@example"],
                 ["worker", "--redis-url", "redis://:secret@localhost:6379/0"],  # a password on the argv
                 ["serve", "--redis-url", "localhost:6379", "--data-dir", str(tmp_path)],
                 ["reducer", "--redis-url", "redis://:secret@localhost:6379/0"],
                 ["serve", "--workers", "-1", "--data-dir", str(tmp_path)],
                 ["serve", "--reducers", "-1", "--data-dir", str(tmp_path)]):
        proc = subprocess.run([str(PHOTONFARM), *args], capture_output=True, text=True, timeout=60)
        assert proc.returncode == 2 and "Traceback" not in proc.stderr, (args, proc.stderr)
        assert proc.stderr.strip().splitlines()[-1].startswith("photonfarm"), proc.stderr
        assert "secret" not in proc.stderr  # a URL may carry a password: it is not echoed


def test_a_burst_worker_gives_up_on_a_redis_it_cannot_reach() -> None:
    """A --burst worker is there to drain the queues and exit: with Redis out of reach (here a
    port nothing listens on) it retries, backing off, and exits 1 after BURST_PATIENCE_SECONDS
    with that said in its log. It waited forever."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]  # closed again: nothing listens there
    start = time.monotonic()
    proc = subprocess.run([str(PHOTONFARM), "worker", "--burst", "--redis-url", f"redis://127.0.0.1:{port}"],
                          capture_output=True, text=True, timeout=BURST_PATIENCE_SECONDS + 40)
    took = time.monotonic() - start
    assert proc.returncode == 1 and "Traceback" not in proc.stderr, proc.stderr[-2000:]
    # The heartbeat thread may log its own warning after the main loop's last line.
    logged = [json.loads(line) for line in proc.stderr.splitlines() if line.startswith("{")]
    errors = [e["msg"] for e in logged if e["level"] == "error"]
    assert len(errors) == 1 and "gives up" in errors[0], proc.stderr[-2000:]
    assert BURST_PATIENCE_SECONDS <= took < BURST_PATIENCE_SECONDS + 30, took
