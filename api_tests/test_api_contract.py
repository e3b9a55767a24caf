"""The API does what its description says (issue 52, items 7, 9 and 10): settings are strict
(no string or boolean taken for a number), a 405 names every method of its path, the images
carry validators (an unchanged one costs a 304), and schema fuzzing (schemathesis, every
check) finds no server error and no disagreement with the OpenAPI description."""

from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import jsonschema_rs
import pytest

from api_tests.cluster import Cluster, finished

# A valid value of each numeric or boolean setting: sent as a string or a boolean instead, it is refused.
VALID: dict[str, Any] = {"target_acceptance": 0.3, "alpha": 0.5, "photons_per_pass": 1024, "initial_radius": 0.1,
                         "hash_entries_per_photon": 2.0, "seed": 3, "max_bounces": 8, "confidence": 0.5,
                         "max_passes": 5, "max_seconds": 5.0, "error_threshold": 0.5, "error_estimation": False}
SMALL = {"resolution": [16, 16], "photons_per_pass": 1024, "max_passes": 3}
FUZZ_SEED = 52
FUZZ_EXAMPLES = 300  # per operation: bounded so that the run stays within about two minutes on two shared cores
# What the schema cannot say, each for a reason; every other check runs on every operation.
# use_after_free: DELETE of an active job cancels it (202) and keeps its image; only a finished
# job is deleted (204), and its routes then answer 404.
FUZZ_EXCLUDED_CHECKS = "use_after_free"
FUZZ_CONFIG = """
# 422 for schema-valid data that breaks a rule JSON Schema cannot state: the pixels of a job
# (a product of its sides), a scene's content (its geometry, its references), an upload's
# archive (its files), a pixel of the job's image (the job's size).
[[operations]]
include-path = "/v1/jobs"
include-method = "POST"
checks.positive_data_acceptance.expected-statuses = ["2xx", "401", "404", "409", "422", "429"]

[[operations]]
include-path = "/v1/jobs/upload"
checks.positive_data_acceptance.expected-statuses = ["2xx", "401", "404", "409", "422", "429"]

[[operations]]
include-path = "/v1/jobs/{job_id}/pixel"
checks.positive_data_acceptance.expected-statuses = ["2xx", "401", "404", "409", "422", "429"]
"""


def _coerced(value: Any) -> list[Any]:
    """What a lax parser would take for `value`: its string, and a boolean (unless it is one)."""
    return [json.dumps(value)] + ([] if isinstance(value, bool) else [True])


@pytest.mark.parametrize(("field", "value"), [(f, v) for f, good in VALID.items() for v in _coerced(good)])
def test_a_string_or_boolean_for_a_number_is_refused(cluster: Cluster, field: str, value: Any) -> None:
    resp = cluster.http.post("/v1/jobs", json={"scene_name": "cornell-box", "settings": {**SMALL, field: value}})
    assert resp.status_code == 422, resp.text
    assert ["body", "settings", field] in [d["loc"] for d in resp.json()["detail"]]


def test_resolution_sides_are_numbers(cluster: Cluster) -> None:
    resp = cluster.http.post("/v1/jobs", json={"scene_name": "cornell-box",
                                               "settings": {**SMALL, "resolution": ["16", "16"]}})
    assert resp.status_code == 422, resp.text
    assert resp.json()["detail"][0]["loc"][:3] == ["body", "settings", "resolution"]


def test_upload_settings_are_strict(cluster: Cluster) -> None:
    scene = json.dumps({"camera": {"position": [0, 0, 5], "look_at": [0, 0, 0], "resolution": [16, 16]},
                        "materials": {"white": {"type": "diffuse", "albedo": [0.5, 0.5, 0.5]}},
                        "shapes": [{"type": "sphere", "center": [0, 0, 0], "radius": 1, "material": "white"}],
                        "lights": [{"type": "point", "position": [0, 2, 2], "power": [10, 10, 10]}]})
    resp = cluster.http.post("/v1/jobs/upload", data={"scene": "s.json", "settings": '{"max_passes": "5"}'},
                             files={"files": ("s.json", scene.encode())})
    assert resp.status_code == 422, resp.text
    assert resp.json()["detail"][0]["loc"] == ["body", "settings", "max_passes"]


def test_a_scene_number_given_as_a_string_is_refused(cluster: Cluster) -> None:
    scene = json.loads(cluster.http.get("/v1/scenes/cornell-box").text)
    scene["camera"]["fov"] = str(scene["camera"].get("fov", 40))
    resp = cluster.http.post("/v1/jobs", json={"scene": scene, "settings": SMALL})
    assert resp.status_code == 422, resp.text
    assert resp.json()["detail"][0]["loc"] == ["body", "scene", "camera", "fov"]


@pytest.mark.parametrize(("method", "path", "allowed"), [("PUT", "/v1/jobs", {"GET", "POST"}),
                                                         ("PATCH", "/v1/jobs/nosuchjob", {"GET", "DELETE"}),
                                                         ("POST", "/v1/jobs/nosuchjob/image", {"GET"}),
                                                         ("POST", "/openapi.json", {"GET", "HEAD"}),
                                                         ("POST", "/static/viewer.js", {"GET", "HEAD"})])
def test_405_names_every_method_of_the_path(cluster: Cluster, method: str, path: str, allowed: set[str]) -> None:
    resp = cluster.http.request(method, path)
    assert resp.status_code == 405, resp.text
    assert {m.strip() for m in resp.headers["Allow"].split(",")} == allowed


@pytest.mark.parametrize("route", ["image", "error"])
@pytest.mark.parametrize("fmt", ["png", "exr"])
def test_an_unchanged_image_costs_a_304(cluster: Cluster, route: str, fmt: str) -> None:
    job = cluster.submit(scene_name="cornell-box", settings=SMALL)
    job = cluster.wait(job["id"], lambda j: finished(j) and j["image_passes"] == j["passes"])
    url = f"/v1/jobs/{job['id']}/{route}?format={fmt}"
    first = cluster.http.get(url)
    assert first.status_code == 200, first.text
    tag = first.headers["ETag"]
    assert tag.startswith('"') and tag.endswith('"')  # strong
    assert first.headers["Cache-Control"] == "no-cache"
    again = cluster.http.get(url, headers={"If-None-Match": tag})
    assert again.status_code == 304
    assert again.content == b""
    assert again.headers["ETag"] == tag
    among = cluster.http.get(url, headers={"If-None-Match": f'"other", W/{tag}'})  # weak comparison (RFC 9110)
    assert among.status_code == 304
    stale = cluster.http.get(url, headers={"If-None-Match": '"other"'})
    assert stale.status_code == 200
    assert stale.content == first.content
    other = "error" if route == "image" else "image"
    assert cluster.http.get(f"/v1/jobs/{job['id']}/{other}?format={fmt}").headers["ETag"] != tag


def test_the_etag_follows_the_image(cluster: Cluster) -> None:
    """A new fold is a new tag: a client holding the tag of an earlier image gets the new one."""
    job = cluster.submit(scene_name="cornell-box", settings={**SMALL, "max_passes": 10_000})
    url = f"/v1/jobs/{job['id']}/image?format=png"
    cluster.wait(job["id"], lambda j: j["image_passes"] >= 1)
    early = cluster.http.get(url)
    passes = int(early.headers["X-Passes"])
    cluster.wait(job["id"], lambda j: j["image_passes"] > passes)
    later = cluster.http.get(url, headers={"If-None-Match": early.headers["ETag"]})
    cluster.http.delete(job["links"]["self"])
    assert later.status_code == 200
    assert int(later.headers["X-Passes"]) > passes
    assert later.headers["ETag"] != early.headers["ETag"]
    assert later.content != early.content


@pytest.fixture(scope="module")
def idle_cluster(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Cluster]:
    """A cluster without workers: the jobs fuzzing submits wait in the queue and take no CPU."""
    c = Cluster(tmp_path_factory.mktemp("idle"), workers=0)
    yield c
    c.close()


def test_schema_fuzzing_finds_no_server_error_and_no_disagreement(idle_cluster: Cluster, tmp_path: Path) -> None:
    """schemathesis over every operation, every check, a fixed seed and a bounded number of cases."""
    config = tmp_path / "schemathesis.toml"
    config.write_text(FUZZ_CONFIG)
    cmd = [str(Path(sys.executable).parent / "schemathesis"), "--config-file", str(config), "run",
           f"http://127.0.0.1:{idle_cluster.port}/openapi.json",
           "--checks", "all", "--exclude-checks", FUZZ_EXCLUDED_CHECKS,
           "--seed", str(FUZZ_SEED), "--max-examples", str(FUZZ_EXAMPLES),
           "--workers", "1", "--request-timeout", "30", "--no-color"]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=600, cwd=tmp_path)  # its cache goes there
    assert done.returncode == 0, done.stdout[-20000:] + done.stderr[-5000:]


def test_the_schema_refuses_what_the_api_refuses(cluster: Cluster) -> None:
    """The values the API refuses lie outside its description: a side of 0, an unknown scene
    name, an adaptive sampler with a method that traces no photons, both scene and scene_name."""
    schema = cluster.http.get("/openapi.json").json()
    request = {"$ref": "#/components/schemas/JobRequest", "components": schema["components"]}
    validator = jsonschema_rs.Draft202012Validator(request)
    assert validator.is_valid({"scene_name": "cornell-box", "settings": {"resolution": [16, 16]}})
    for refused in ({"scene_name": "cornell-box", "settings": {"resolution": [0, 0]}},
                    {"scene_name": "0"},
                    {"scene_name": "cornell-box", "settings": {"method": "vcm", "sampler": "adaptive"}},
                    {"scene_name": "cornell-box", "settings": {"error_threshold": 0.1, "error_estimation": False}},
                    {"scene_name": "cornell-box", "scene": {}}, {}):
        assert not validator.is_valid(refused), refused
        assert cluster.http.post("/v1/jobs", json=refused).status_code == 422, refused
