"""The API's scene loads in child processes (service/scene_loader.py): a load through the
loader gives what the same load in this process gives; a bad scene comes back as the same
SceneError (a limit as a SceneLimitError) with its field; a load past the wall-clock limit
is killed and refused as LoadUnavailable, and the loader serves the next load."""

from __future__ import annotations

import json
import os
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import redis

from service.scene_loader import LoadUnavailable, SceneLoader, SceneRequest, load_now
from tests.helpers import SENSOR, xml
from worker.scene import (
    SCENES_DIR,
    SceneError,
    SceneLimitError,
    bundled_scene_path,
    inline_json,
    inline_meshes,
    load_any_scene,
    parse_scene,
)
from worker.settings import Settings
from worker.store import Jobs


@pytest.fixture(scope="module")
def loader() -> SceneLoader:
    return SceneLoader(seconds=120)


def test_a_load_in_a_child_matches_one_in_this_process(loader: SceneLoader) -> None:
    for request in (SceneRequest(scene_name="cornell-box"),
                    SceneRequest(scene=json.loads((SCENES_DIR / "cornell-box.json").read_text())),
                    SceneRequest(path=SCENES_DIR / "mitsuba" / "ply-mesh.xml", root=SCENES_DIR / "mitsuba")):
        assert loader.load(request) == load_now(request)


def test_errors_come_back_with_their_kind_and_field(loader: SceneLoader, tmp_path: Path) -> None:
    scene = json.loads((SCENES_DIR / "cornell-box.json").read_text())
    scene["shapes"][1]["material"] = "nothing"
    with pytest.raises(SceneError) as info:
        loader.load(SceneRequest(scene=scene))
    assert type(info.value) is SceneError and info.value.field == "shapes.1.material", info.value
    (tmp_path / "leaf.xml").write_text(xml(""))
    (tmp_path / "mid.xml").write_text(xml('<include filename="leaf.xml"/>\n' * 40))
    (tmp_path / "scene.xml").write_text(xml(SENSOR + '\n<include filename="mid.xml"/>' * 40))
    with pytest.raises(SceneLimitError) as limit:
        loader.load(SceneRequest(path=tmp_path / "scene.xml", root=tmp_path))
    assert limit.value.field == "mid.xml" and "scene files" in limit.value.message, limit.value


def test_a_load_past_the_time_limit_is_killed_and_the_loader_serves_on(loader: SceneLoader, tmp_path: Path) -> None:
    """A FIFO named as the scene: the child blocks reading it until it is killed."""
    fifo = tmp_path / "scene.json"
    os.mkfifo(fifo)
    quick = SceneLoader(processes=1, seconds=3)
    start = time.monotonic()
    with pytest.raises(LoadUnavailable, match="did not load within 3 s"):
        quick.load(SceneRequest(path=fifo, root=tmp_path))
    assert time.monotonic() - start < 30
    assert quick.load(SceneRequest(scene_name="cornell-box")) == load_now(SceneRequest(scene_name="cornell-box"))


def test_loads_past_the_slots_and_the_queue_are_refused_at_once(tmp_path: Path) -> None:
    """One slot, no queue: while a load blocks (on a FIFO), the next is refused, not queued;
    a bundled scene, loaded in the API's process once, is answered all the same."""
    fifo = tmp_path / "scene.json"
    os.mkfifo(fifo)
    busy = SceneLoader(processes=1, seconds=5, queue=0)
    blocked = threading.Thread(target=lambda: pytest.raises(LoadUnavailable, busy.load,
                                                            SceneRequest(path=fifo, root=tmp_path)))
    blocked.start()
    time.sleep(1.0)  # the blocked load takes its slot as it starts
    posted = json.loads(bundled_scene_path("cornell-box").read_text())
    with pytest.raises(LoadUnavailable, match="others wait for one"):  # refused, not timed out waiting
        busy.load(SceneRequest(scene=posted))
    assert busy.load(SceneRequest(scene_name="cornell-box")) == load_now(SceneRequest(scene_name="cornell-box"))
    blocked.join()
    assert busy.load(SceneRequest(scene=posted)) == load_now(SceneRequest(scene=posted))


@pytest.mark.parametrize("name", ["cornell-box.json", "mitsuba/ply-mesh.xml", "mitsuba/obj-mesh.xml"])
def test_inline_json_is_the_inlined_scene_encoded(name: str) -> None:
    path = SCENES_DIR / name
    scene, base_dir = load_any_scene(path)
    assert json.loads(inline_json(scene, base_dir, path.parent)) == inline_meshes(scene, base_dir, path.parent)


@pytest.mark.parametrize("name", ["mitsuba/ply-mesh.xml", "mitsuba/obj-mesh.xml"])
def test_a_jobs_scene_reaches_a_worker_as_it_was_loaded(name: str, redis_url: str) -> None:
    """The load holds meshes as arrays; the job's scene is JSON text in Redis, and what a
    worker on any machine parses from it is the same scene, every coordinate to the bit."""
    path = SCENES_DIR / name
    loaded = load_now(SceneRequest(path=path, root=path.parent))
    jobs = Jobs(redis.Redis.from_url(redis_url))
    job_id = jobs.create(loaded.scene_json, Settings(resolution=(8, 8)), 8, 8, None)
    received = parse_scene(jobs.scene(job_id))
    scene, _ = load_any_scene(path)
    assert received == scene
    meshes = [(a, b) for a, b in zip(received.shapes, scene.shapes, strict=True) if a.type == "mesh"]
    assert meshes  # ply-mesh.xml's has normals (test_scene_import.py, test_scenes_use_what_they_claim)
    for a, b in meshes:
        for key in ("vertices", "triangles", "normals"):
            assert np.array_equal(getattr(a, key), getattr(b, key)), key
