"""Scene uploads (POST /v1/jobs/upload) against a real cluster: a Mitsuba XML scene with
its PLY mesh renders from an archive or from several files; each bad upload gets one clear
error naming its field (422) or its size (413), and the service keeps serving after it;
`photonfarm submit` sends a scene with an .obj beside it."""

from __future__ import annotations

import io
import json
import re
import stat
import subprocess
import sys
import tarfile
import zipfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from api_tests.cluster import Cluster, finished
from api_tests.helpers import zip_bomb, zip_bytes
from service.upload import MAX_UPLOAD_BYTES, MAX_UPLOAD_FILES
from worker.scene import SCENES_DIR, load_any_scene
from worker.store.record import MAX_JOB_NOTES, MAX_NOTE_CHARS

MITSUBA = SCENES_DIR / "mitsuba"
PLY_SCENE = {"ply-mesh.xml": MITSUBA / "ply-mesh.xml", "room.xml": MITSUBA / "room.xml",
             "meshes/icosphere.ply": MITSUBA / "meshes" / "icosphere.ply"}
PASSES, P = 3, 4096
# Uniform photons: the notes these tests check are the scene's alone (sampler auto adds its own
# after them, api_tests/test_sampler_auto.py).
SETTINGS = {"max_passes": PASSES, "photons_per_pass": P, "resolution": [24, 24], "seed": 5, "sampler": "uniform"}


@pytest.fixture(scope="module")
def cluster(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Cluster]:
    c = Cluster(tmp_path_factory.mktemp("upload"), workers=1)
    yield c
    c.close()


def _zip_link(name: str, target: str) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as z:
        info = zipfile.ZipInfo(name)
        info.external_attr = (stat.S_IFLNK | 0o777) << 16
        z.writestr(info, target)
    return buf.getvalue()


def _encrypted_zip(name: str, data: bytes) -> bytes:
    """A zip whose member says it is encrypted (flag bit 0): no password is ever sent."""
    raw = bytearray(zip_bytes({name: data}))
    for signature, flags_at in ((b"PK\x03\x04", 6), (b"PK\x01\x02", 8)):  # local and central headers
        raw[raw.index(signature) + flags_at] |= 0x1
    return bytes(raw)


def _tar(entries: dict[str, bytes], links: dict[str, str] | None = None, top: bool = False,
         folders: list[str] | None = None) -> bytes:
    """A .tar.gz; `top` adds the "./" folder entry that `tar -C DIR .` writes first."""
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:gz") as t:
        for name in (["./"] if top else []) + (folders or []):
            folder = tarfile.TarInfo(name)
            folder.type = tarfile.DIRTYPE
            t.addfile(folder)
        for name, data in entries.items():
            info = tarfile.TarInfo(name)
            info.size = len(data)
            t.addfile(info, io.BytesIO(data))
        for name, target in (links or {}).items():
            info = tarfile.TarInfo(name)
            info.type, info.linkname = tarfile.SYMTYPE, target
            t.addfile(info)
    return buf.getvalue()


def _files(entries: dict[str, Path]) -> dict[str, bytes]:
    return {name: path.read_bytes() for name, path in entries.items()}


def _upload(c: Cluster, scene: str, archive: tuple[str, bytes] | None = None,
            files: dict[str, bytes] | None = None, settings: dict[str, Any] | None = None) -> httpx.Response:
    parts = [("archive", archive)] if archive else [("files", (n, d)) for n, d in (files or {}).items()]
    return c.http.post("/v1/jobs/upload", files=parts,
                       data={"scene": scene, "settings": json.dumps(settings or SETTINGS)})


def _still_serving(c: Cluster) -> None:
    assert c.http.get("/healthz").status_code == 200
    assert c.http.get("/v1/jobs").status_code == 200


@pytest.mark.parametrize("form", ["zip", "tar.gz", "tar.gz of ./", "files"])
def test_mitsuba_xml_with_its_ply_renders_to_the_exact_totals(cluster: Cluster, form: str) -> None:
    entries = _files(PLY_SCENE)
    if form == "files":
        resp = _upload(cluster, "ply-mesh.xml", files=entries)
    elif form == "zip":
        resp = _upload(cluster, "ply-mesh.xml", archive=("scene.zip", zip_bytes(entries)))
    else:
        dot = form == "tar.gz of ./"
        archive = _tar({f"./{name}" if dot else name: data for name, data in entries.items()}, top=dot)
        resp = _upload(cluster, "ply-mesh.xml", archive=("scene.tar.gz", archive))
    assert resp.status_code == 201, resp.text
    job = resp.json()
    assert resp.headers["location"] == f"/v1/jobs/{job['id']}"
    assert (job["width"], job["height"]) == (24, 24) and job["scene_name"] is None
    done = cluster.wait(job["id"], finished, timeout=180)
    assert done["status"] == "completed", done
    assert done["passes"] == PASSES and done["photons"] == PASSES * P, done
    image = cluster.http.get(job["links"]["image_png"])
    assert image.status_code == 200 and image.content[:8] == b"\x89PNG\r\n\x1a\n"


def test_mitsuba_search_paths_and_notes(cluster: Cluster) -> None:
    """A scene whose files are found through <path> and from a fragment in a subfolder renders
    from an upload; what the scene holds that was ignored is kept with the job: in the answer
    to the submission and in every view of the job after it, to its end."""
    names = ["search-paths.xml", "room.xml", "fragments/objects.xml", "fragments/block.xml", "meshes/gem.obj",
             "shared/blob.serialized", "spectral-box.xml", "spectra/teal.spd"]
    entries = {name: (MITSUBA / name).read_bytes() for name in names}
    resp = _upload(cluster, "search-paths.xml", archive=("scene.zip", zip_bytes(entries)))
    assert resp.status_code == 201, resp.text
    [note] = resp.json()["notes"]
    assert note.startswith('ignored: search-paths.xml line 8: <integrator type="path">'), note
    done = cluster.wait(resp.json()["id"], finished, timeout=180)
    assert done["status"] == "completed" and done["passes"] == PASSES, done
    assert done["notes"] == [note], done["notes"]
    resp = _upload(cluster, "spectral-box.xml", archive=("scene.zip", zip_bytes(entries)))
    assert resp.status_code == 201, resp.text
    notes = resp.json()["notes"]
    assert any("focus_distance" in n for n in notes) and all(n.startswith("ignored: ") for n in notes), notes
    assert cluster.job(resp.json()["id"])["notes"] == notes
    plain = cluster.http.post("/v1/jobs", json={"scene_name": "cornell-box", "settings": SETTINGS})
    assert plain.status_code == 201 and plain.json()["notes"] == [], plain.text
    cluster.wait(plain.json()["id"], finished, timeout=180)
    cluster.wait(resp.json()["id"], finished, timeout=180)


def test_thousands_of_ignored_properties_keep_a_bounded_record(cluster: Cluster, tmp_path: Path) -> None:
    """A scene with thousands of textures nothing refers to (each noted: Mitsuba loads and never
    renders them), the first with a very long id: the job keeps the first distinct notes, the
    long one cut, and a last line counting the rest, the same on every view of the job."""
    long_id = "t" * 4 * MAX_NOTE_CHARS
    textures = "".join(f'<texture type="bitmap" id="{long_id if i == 0 else f"t{i}"}"/>\n' for i in range(3000))
    text = (MITSUBA / "ply-mesh.xml").read_text().replace("</scene>", textures + "</scene>")
    entries = {**_files(PLY_SCENE), "ply-mesh.xml": text.encode()}
    for name, data in entries.items():  # the same scene read here: every note it yields
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_bytes(data)
    every: list[str] = []
    load_any_scene(tmp_path / "ply-mesh.xml", notes=every)
    assert len(every) > 3000 and len(every) == len(set(every))
    resp = _upload(cluster, "ply-mesh.xml", archive=("scene.zip", zip_bytes(entries)))
    assert resp.status_code == 201, resp.text
    notes = resp.json()["notes"]
    assert len(notes) == MAX_JOB_NOTES + 1 and notes[-1] == f"... and {len(every) - MAX_JOB_NOTES} more", notes
    for kept, note in zip(notes[:-1], every[:MAX_JOB_NOTES], strict=True):
        if len(note) <= MAX_NOTE_CHARS:
            assert kept == note
        else:  # cut
            assert len(kept) == MAX_NOTE_CHARS and kept.endswith("...") and note.startswith(kept[:-3]), kept
    assert any(long_id[:100] in note for note in notes), "the long note is among those kept"
    done = cluster.wait(resp.json()["id"], finished, timeout=180)
    assert done["status"] == "completed" and done["notes"] == notes, done["status"]
    listed = cluster.http.get("/v1/jobs", params={"limit": 500}).json()
    assert next(job for job in listed if job["id"] == done["id"])["notes"] == notes


def _scene_xml(shape: str) -> bytes:
    """ply-mesh.xml with its PLY shape replaced by `shape`."""
    text = (MITSUBA / "ply-mesh.xml").read_text()
    start = text.index('<shape type="ply">')
    end = text.index("</shape>", start) + len("</shape>")
    return (text[:start] + shape + text[end:]).encode()


def _bad_uploads() -> dict[str, tuple[dict[str, Any], int, list[str], str]]:
    """name: (upload arguments, status, loc, words of the message)."""
    room = (MITSUBA / "room.xml").read_bytes()
    ply = (MITSUBA / "meshes" / "icosphere.ply").read_bytes()
    hair = _scene_xml('<shape type="sphere"><bsdf type="hair"/></shape>')
    missing = _scene_xml('<shape type="ply"><string name="filename" value="meshes/none.ply"/><ref id="white"/></shape>')
    outside = _scene_xml(f'<shape type="ply"><string name="filename" value="{MITSUBA / "meshes" / "icosphere.ply"}"/>'
                         '<ref id="white"/></shape>')
    long_mesh = _scene_xml(f'<shape type="ply"><string name="filename" value="{"m" * 300}.ply"/></shape>')
    long_include = _scene_xml(f'<include filename="{"i" * 300}.xml"/>')
    deep = _scene_xml('<shape type="sphere">' + "<bsdf>" * 1000 + "</bsdf>" * 1000 + "</shape>")
    return {
        "unknown plugin": ({"files": {"s.xml": hair, "room.xml": room}}, 422, ["body", "scene", "s.xml"],
                           "unknown bsdf plugin 'hair'"),
        "participating medium": ({"files": {"s.xml": _scene_xml('<shape type="sphere"><medium type="homogeneous" '
                                                                 'name="interior"/></shape>'), "room.xml": room}},
                                 422, ["body", "scene", "s.xml"], "participating media are not supported"),
        "missing mesh": ({"files": {"s.xml": missing, "room.xml": room}}, 422, ["body", "scene", "s.xml"],
                         "'meshes/none.ply' not found"),
        "broken PLY": ({"scene": "ply-mesh.xml", "files": {"ply-mesh.xml": (MITSUBA / "ply-mesh.xml").read_bytes(),
                                                            "room.xml": room, "meshes/icosphere.ply": ply[:300]}},
                       422, ["body", "scene", "ply-mesh.xml"],
                       "icosphere.ply"),
        "mesh path outside the upload": ({"files": {"s.xml": outside, "room.xml": room}}, 422,
                                         ["body", "scene", "s.xml"], "leaves the scene's directory"),
        "archive entry with ..": ({"archive": ("a.zip", zip_bytes({"s.xml": hair, "../evil.ply": ply}))}, 422,
                                  ["body", "archive"], "outside the upload"),
        "archive folder ..": ({"archive": ("a.tar.gz", _tar({"s.xml": hair}, folders=["../"]))}, 422,
                              ["body", "archive"], "outside the upload"),
        "absolute archive entry": ({"archive": ("a.tar.gz", _tar({"/tmp/evil.ply": ply}))}, 422,
                                   ["body", "archive"], "outside the upload"),
        "symlink in the archive": ({"archive": ("a.tar.gz", _tar({"s.xml": hair}, {"m.ply": "/etc/passwd"}))}, 422,
                                   ["body", "archive"], "link"),
        "symlink in a zip": ({"archive": ("a.zip", _zip_link("meshes/icosphere.ply", "/etc/passwd"))}, 422,
                             ["body", "archive"], "link"),
        "file name with ..": ({"files": {"../s.xml": hair}}, 422, ["body", "files"], "outside the upload"),
        "scene not in the upload": ({"files": {"room.xml": room}, "scene": "s.xml"}, 422, ["body", "scene"],
                                    "not in the upload"),
        "not an archive": ({"archive": ("a.zip", b"PK\x03\x04 not a zip")}, 422, ["body", "archive"],
                           "not a readable archive"),
        "truncated archive": ({"archive": ("a.tar.gz", _tar({"s.xml": hair, "room.xml": room})[:200])}, 422,
                              ["body", "archive"], "not a readable archive"),
        "archive of no known kind": ({"archive": ("scene.rar", b"Rar!")}, 422, ["body", "archive"],
                                     "an archive is a .zip"),
        "encrypted zip": ({"archive": ("a.zip", _encrypted_zip("s.xml", hair))}, 422, ["body", "archive"],
                          "not a readable archive"),
        "bad settings": ({"files": {"s.xml": hair}, "settings": {"alpha": 7}}, 422, ["body", "settings", "alpha"],
                         "less than"),
        "zip file and folder a/b": ({"archive": ("a.zip", zip_bytes({"a": ply, "a/b": ply}))}, 422, ["body", "archive"],
                                    "'a/b': 'a' is both a file and a folder"),
        "zip file and folder a/": ({"archive": ("a.zip", zip_bytes({"a": ply, "a/": b""}))}, 422, ["body", "archive"],
                                   "'a/': 'a' is both a file and a folder"),
        "tar file and folder a/b": ({"archive": ("a.tar.gz", _tar({"a": ply, "a/b": ply}))}, 422, ["body", "archive"],
                                    "'a/b': 'a' is both a file and a folder"),
        "files file and folder a/b": ({"files": {"a": ply, "a/b": ply}}, 422, ["body", "files"],
                                      "'a/b': 'a' is both a file and a folder"),
        "the same file twice": ({"files": {"a": ply, "./a": ply}}, 422, ["body", "files"], "'./a' appears twice"),
        "mesh name too long": ({"files": {"s.xml": long_mesh, "room.xml": room}}, 422, ["body", "scene", "s.xml"],
                               "File name too long"),
        "include name too long": ({"files": {"s.xml": long_include, "room.xml": room}}, 422,
                                  ["body", "scene", "s.xml"], "File name too long"),
        "XML nested 1,000 deep": ({"files": {"s.xml": deep, "room.xml": room}}, 422, ["body", "scene", "s.xml"],
                                  "nested deeper than"),
    }


@pytest.mark.parametrize("name", list(_bad_uploads()))
def test_a_bad_upload_gets_one_clear_error_and_the_service_serves_on(cluster: Cluster, name: str) -> None:
    args, status, loc, words = _bad_uploads()[name]
    resp = _upload(cluster, **{"scene": "s.xml", **args})
    assert resp.status_code == status, resp.text
    detail = resp.json()["detail"]
    assert len(detail) == 1 and detail[0]["loc"] == loc and words in detail[0]["msg"], detail
    _still_serving(cluster)


def test_a_malformed_form_is_422_naming_the_body(cluster: Cluster) -> None:
    resp = cluster.http.post("/v1/jobs/upload", content=b"--x\r\nnot a part",
                             headers={"content-type": "multipart/form-data"})  # no boundary
    assert resp.status_code == 422 and resp.json()["detail"][0]["loc"] == ["body"], resp.text
    assert "not a readable form" in resp.json()["detail"][0]["msg"]
    _still_serving(cluster)


def test_an_archive_that_unpacks_past_the_limit_is_refused_413(cluster: Cluster) -> None:
    """A zip bomb: a small archive (about 130 KB) of zeros that unpacks past the byte limit."""
    bomb = zip_bomb()
    assert len(bomb) < MAX_UPLOAD_BYTES // 100
    resp = _upload(cluster, "s.xml", archive=("bomb.zip", bomb))
    detail = resp.json()["detail"]
    assert resp.status_code == 413 and f"larger than {MAX_UPLOAD_BYTES} bytes" in detail, detail
    assert "'zeros.ply'" in detail  # the member, named
    _still_serving(cluster)


def test_too_many_files_are_refused_413(cluster: Cluster) -> None:
    entries = {f"f{i}.ply": b"" for i in range(MAX_UPLOAD_FILES + 1)}
    resp = _upload(cluster, "f0.ply", archive=("many.tar.gz", _tar(entries)))
    assert resp.status_code == 413 and f"more than {MAX_UPLOAD_FILES} files" in resp.json()["detail"], resp.text
    _still_serving(cluster)


def test_photonfarm_submit_sends_a_scene_with_its_obj_beside_it(cluster: Cluster, tmp_path: Path) -> None:
    """A JSON scene naming an .obj in its own folder (not under scenes/): submit uploads both."""
    folder = tmp_path / "my scene"
    folder.mkdir()
    (folder / "gem.obj").write_bytes((MITSUBA / "meshes" / "gem.obj").read_bytes())
    scene = json.loads((SCENES_DIR / "cornell-box.json").read_text())
    scene["shapes"].append({"type": "mesh", "file": "gem.obj", "material": "white"})
    (folder / "scene.json").write_text(json.dumps(scene))
    out = tmp_path / "out.png"
    run = subprocess.run([sys.executable, "-m", "service.cli", "submit", str(folder / "scene.json"),
                          "--url", str(cluster.http.base_url), "--max-passes", "2", "--photons-per-pass", "4096",
                          "--resolution", "16x16", "--watch", "--poll", "0.3", "--out", str(out)],
                         capture_output=True, text=True, timeout=240, env=cluster.env)
    assert run.returncode == 0, run.stderr
    assert "completed: 2 passes, 8192 photons" in run.stdout, run.stdout
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # A Mitsuba scene goes as an upload too, with the XML it includes and its meshes.
    run = subprocess.run([sys.executable, "-m", "service.cli", "submit", str(MITSUBA / "obj-mesh.xml"),
                          "--url", str(cluster.http.base_url), "--max-passes", "2", "--photons-per-pass", "4096",
                          "--resolution", "16x16"], capture_output=True, text=True, timeout=60, env=cluster.env)
    assert run.returncode == 0, run.stderr
    job_id = re.match(r"job (\S+) ", run.stdout).group(1)
    done = cluster.wait(job_id, finished, timeout=180)
    assert done["status"] == "completed" and done["photons"] == 2 * 4096, done
    # One with a serialized mesh found through <path>: sent too; what it ignores is printed once
    # while it is watched, as the job keeps it.
    run = subprocess.run([sys.executable, "-m", "service.cli", "submit", str(MITSUBA / "search-paths.xml"),
                          "--url", str(cluster.http.base_url), "--max-passes", "2", "--photons-per-pass", "4096",
                          "--resolution", "16x16", "--watch", "--poll", "0.3", "--out", str(tmp_path / "notes.png")],
                         capture_output=True, text=True, timeout=240, env=cluster.env)
    assert run.returncode == 0, run.stderr
    assert "completed: 2 passes, 8192 photons" in run.stdout, run.stdout
    printed = [line.removeprefix("photonfarm: ") for line in run.stderr.splitlines() if "ignored: " in line]
    kept = cluster.job(re.match(r"job (\S+) ", run.stdout).group(1))["notes"]
    assert printed == [note for note in kept if "ignored: " in note], run.stderr  # (sampler auto's follow them)
    assert len(printed) == 1 and printed[0].startswith("ignored: search-paths.xml line 8: <integrator"), printed
    # The same scene without its mesh beside it is refused by the service, naming the mesh.
    (folder / "gem.obj").unlink()
    run = subprocess.run([sys.executable, "-m", "service.cli", "submit", str(folder / "scene.json"),
                          "--url", str(cluster.http.base_url)], capture_output=True, text=True, timeout=60,
                         env=cluster.env)
    assert run.returncode != 0 and "HTTP 422" in run.stderr and "gem.obj" in run.stderr, run.stderr
    assert "Traceback" not in run.stderr


def test_submit_refuses_a_folder_past_the_upload_limits_in_one_line(cluster: Cluster, tmp_path: Path) -> None:
    for i in range(MAX_UPLOAD_FILES + 1):
        (tmp_path / f"m{i}.obj").write_text("")
    (tmp_path / "scene.xml").write_text("<scene version='3.0.0'/>")
    run = subprocess.run([sys.executable, "-m", "service.cli", "submit", str(tmp_path / "scene.xml"),
                          "--url", str(cluster.http.base_url)], capture_output=True, text=True, timeout=60,
                         env=cluster.env)
    assert run.returncode != 0 and "put the scene in a folder of its own" in run.stderr, run.stderr
    assert len(run.stderr.strip().splitlines()) == 1


def test_an_include_bomb_is_refused_413_naming_what_ran_out(cluster: Cluster) -> None:
    """A small archive whose includes would open 64,000 files (40 per file, three deep, far
    within the depth limit): the load stops at its file budget, naming the file and line."""
    leaf = b'<scene version="3.0.0"/>'
    entries = {"s.xml": _scene_xml('<include filename="i1.xml"/>' * 40),
               "room.xml": (MITSUBA / "room.xml").read_bytes(),
               "i1.xml": b'<scene version="3.0.0">' + b'<include filename="i2.xml"/>' * 40 + b"</scene>",
               "i2.xml": b'<scene version="3.0.0">' + b'<include filename="i3.xml"/>' * 40 + b"</scene>",
               "i3.xml": leaf}
    archive = zip_bytes(entries)
    assert len(archive) < 8192
    resp = _upload(cluster, "s.xml", archive=("bomb.zip", archive))
    assert resp.status_code == 413, resp.text
    detail = resp.json()["detail"]
    assert re.fullmatch(r"i\d\.xml: line \d+: <include>: the scene needs more than \d+ scene files .*", detail), detail
    _still_serving(cluster)


def test_a_json_integer_past_pythons_digit_limit_is_named_as_such(cluster: Cluster) -> None:
    body = '{"scene_name": "cornell-box", "settings": {"seed": ' + "7" * 5000 + "}}"
    resp = cluster.http.post("/v1/jobs", content=body, headers={"content-type": "application/json"})
    assert resp.status_code == 422, resp.text
    detail = resp.json()["detail"]
    assert detail[0]["loc"] == ["body"] and "integer with more than 4300 digits" in detail[0]["msg"], detail
    _still_serving(cluster)
