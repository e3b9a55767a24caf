"""The total work of one scene load is bounded whatever the scene's shape (worker/scene.py,
LoadBudget): files opened (an included file counts every time it is included), XML
elements and nesting, bytes, mesh files and triangles. Running out is a SceneError naming
what ran out and the file and line where it did; odd names and deep nesting are
SceneErrors too, never an OSError or a RecursionError."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.helpers import SENSOR, xml
from worker.scene import SCENES_DIR, SceneError, inline_meshes, load_any_scene

ROOT = Path(__file__).resolve().parent.parent
TRIANGLE_OBJ = "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n"


def load_error(path: Path) -> SceneError:
    """The SceneError of loading `path` as the service does (meshes inlined)."""
    with pytest.raises(SceneError) as info:
        scene, base_dir = load_any_scene(path)
        inline_meshes(scene, base_dir, path.parent)
    return info.value


def test_an_include_bomb_runs_out_of_files_at_the_include_that_opens_one_too_many(tmp_path: Path) -> None:
    """40 includes of a file that includes 40 others: 1,641 files opened, past the limit,
    though no include is nested deeper than 2."""
    (tmp_path / "leaf.xml").write_text(xml(""))
    (tmp_path / "mid.xml").write_text(xml('<include filename="leaf.xml"/>\n' * 40))
    (tmp_path / "scene.xml").write_text(xml(SENSOR + '\n<include filename="mid.xml"/>' * 40))
    err = load_error(tmp_path / "scene.xml")
    assert err.field == "mid.xml" and "line " in err.message and "<include>" in err.message, err
    assert "more than 1000 scene files" in err.message, err


def test_elements_count_across_every_inclusion(tmp_path: Path) -> None:
    """A file of 2,001 elements included 100 times: 200,100 elements, past the limit."""
    (tmp_path / "big.xml").write_text(xml('<default name="x" value="1"/>\n' * 2000))
    (tmp_path / "scene.xml").write_text(xml(SENSOR + '\n<include filename="big.xml"/>' * 100))
    err = load_error(tmp_path / "scene.xml")
    assert err.field == "big.xml" and "line " in err.message and "more than 200000 XML elements" in err.message, err


def test_mesh_files_count_every_use(tmp_path: Path) -> None:
    """A JSON scene naming one small mesh file 2,001 times: each use opens it again."""
    (tmp_path / "t.obj").write_text(TRIANGLE_OBJ)
    scene = json.loads((SCENES_DIR / "cornell-box.json").read_text())
    scene["shapes"] = [{"type": "mesh", "file": "t.obj", "material": "white"}] * 2001
    (tmp_path / "scene.json").write_text(json.dumps(scene))
    err = load_error(tmp_path / "scene.json")
    assert err.field == "shapes.2000.file" and "more than 2000 mesh files" in err.message, err


def test_xml_nested_past_the_depth_limit_names_the_element(tmp_path: Path) -> None:
    body = '<shape type="sphere">' + "<bsdf>" * 1000 + "</bsdf>" * 1000 + "</shape>"
    (tmp_path / "scene.xml").write_text(xml(SENSOR + "\n" + body))
    err = load_error(tmp_path / "scene.xml")
    assert err.field == "scene.xml" and "line 6: <bsdf>" in err.message, err
    assert "nested deeper than 64 elements" in err.message, err


@pytest.mark.parametrize("element", ['<include filename="{name}.xml"/>',
                                     '<shape type="ply"><string name="filename" value="{name}.ply"/></shape>'])
def test_a_file_name_too_long_for_the_file_system_names_the_element(tmp_path: Path, element: str) -> None:
    (tmp_path / "scene.xml").write_text(xml(SENSOR + "\n" + element.format(name="x" * 300)))
    err = load_error(tmp_path / "scene.xml")
    assert err.field == "scene.xml" and "line 6: <" in err.message and "File name too long" in err.message, err


def test_the_triangle_limit_after_a_conversion_names_the_xml_element(tmp_path: Path, monkeypatch) -> None:
    """A cube (12 triangles) and a rectangle (2) with a limit of 12: the rectangle's line."""
    from worker import mitsuba_scene, scene

    monkeypatch.setattr(mitsuba_scene, "MAX_TRIANGLES", 12)
    monkeypatch.setattr(scene, "MAX_TRIANGLES", 12)
    (tmp_path / "scene.xml").write_text(xml(SENSOR + '\n<shape type="cube"/>\n<shape type="rectangle"/>'))
    err = load_error(tmp_path / "scene.xml")
    assert err.field == "scene.xml" and 'line 7: <shape type="rectangle">' in err.message, err
    assert "more than 12 triangles" in err.message, err


@pytest.mark.parametrize("command", [["render", "--passes", "1", "--out", "{tmp}/x.png"], ["convert"]])
def test_the_cli_says_what_ran_out_in_one_line(tmp_path: Path, command: list[str]) -> None:
    (tmp_path / "leaf.xml").write_text(xml(""))
    (tmp_path / "mid.xml").write_text(xml('<include filename="leaf.xml"/>\n' * 40))
    (tmp_path / "scene.xml").write_text(xml(SENSOR + '\n<include filename="mid.xml"/>' * 40))
    args = [a.format(tmp=tmp_path) for a in command]
    proc = subprocess.run([sys.executable, "-m", "service.cli", *args, str(tmp_path / "scene.xml")],
                          capture_output=True, text=True, timeout=120, env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert proc.returncode == 2 and len(proc.stderr.strip().splitlines()) == 1, proc.stderr
    assert proc.stderr.startswith("photonfarm: bad scene: mid.xml: line "), proc.stderr
    assert "more than 1000 scene files" in proc.stderr, proc.stderr
