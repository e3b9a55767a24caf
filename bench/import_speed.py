"""Import speed: a Mitsuba 3 scene of 500,000 triangles, loaded by us and by Mitsuba 3 (issue 47).

    python -m bench.import_speed

Writes, to a temporary folder, a 500 x 500 quad grid (500,000 triangles, 251,001 vertices)
as a `serialized` file (written by worker/serialized.py's writer) and as a binary PLY, each
in a Mitsuba 3 XML scene, and times, once each and side by side: our load of the scene
(`load_any_scene`: read, convert, validate, as a job's load does), the encoding of the loaded
scene as the job's JSON that the service then stores (`inline_json`), `convert_mitsuba` (the
load ending in the scene's JSON lists, as `photonfarm convert` writes them) and Mitsuba's
`mi.load_file` (scalar_rgb). A small scene is loaded by both first, so imports and first-use
setup are not timed. Prints a table and writes bench/out/import_speed.json; the issue asks
our load to take at most 2x Mitsuba's.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np

from bench.common import write_json
from worker.mitsuba_scene import convert_mitsuba
from worker.scene import MAX_TRIANGLES, inline_json, load_any_scene
from worker.serialized import write_serialized

GRID = 500  # quads per side: 2 * GRID^2 triangles
SCENE = """<scene version="3.0.0">
    <sensor type="perspective"><transform name="to_world"><lookat origin="0, 0, 3" target="0, 0, 0" up="0, 1, 0"/>
    </transform><film type="hdrfilm"><integer name="width" value="64"/><integer name="height" value="64"/></film>
    </sensor>
    <shape type="{kind}"><string name="filename" value="{name}"/></shape>
</scene>
"""


def grid() -> tuple[np.ndarray, np.ndarray]:
    """A GRID x GRID quad grid over [-1, 1]^2 at z = 0, two triangles per quad."""
    t = np.linspace(-1.0, 1.0, GRID + 1)
    x, y = np.meshgrid(t, t)
    vertices = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], axis=1)
    i, j = np.meshgrid(np.arange(GRID), np.arange(GRID))
    a = (j * (GRID + 1) + i).ravel()
    b, c, d = a + 1, a + GRID + 2, a + GRID + 1
    triangles = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return vertices, triangles


def write_scenes(folder: Path) -> dict[str, Path]:
    import trimesh

    vertices, triangles = grid()
    assert len(triangles) == MAX_TRIANGLES
    (folder / "grid.serialized").write_bytes(write_serialized([(vertices, triangles, None)]))
    trimesh.Trimesh(vertices, triangles, process=False).export(folder / "grid.ply", encoding="binary")
    scenes = {}
    for kind, name in (("serialized", "grid.serialized"), ("ply", "grid.ply")):
        scenes[kind] = folder / f"{kind}.xml"
        scenes[kind].write_text(SCENE.format(kind=kind, name=name))
    return scenes


def timed(fn) -> float:
    start = time.perf_counter()
    fn()
    return time.perf_counter() - start


def main() -> None:
    import mitsuba as mi

    mi.set_variant("scalar_rgb")
    mi.set_log_level(mi.LogLevel.Error)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        warm = folder / "warm.xml"
        warm.write_text(SCENE.format(kind="cube", name="none").replace('<string name="filename" value="none"/>', ""))
        load_any_scene(warm), mi.load_file(str(warm))
        for kind, path in write_scenes(folder).items():
            ours = timed(lambda path=path: load_any_scene(path))
            scene, base_dir = load_any_scene(path)
            job_json = timed(lambda scene=scene, base_dir=base_dir: inline_json(scene, base_dir, folder))
            convert = timed(lambda path=path: convert_mitsuba(path))
            theirs = timed(lambda path=path: mi.load_file(str(path)))
            rows.append({"format": kind, "triangles": MAX_TRIANGLES, "file_bytes": (folder / (
                "grid.serialized" if kind == "serialized" else "grid.ply")).stat().st_size,
                "ours_load_s": ours, "ours_job_json_s": job_json, "ours_convert_s": convert,
                "mitsuba_load_s": theirs, "ratio": ours / theirs})
    print(f"{'format':<11}{'triangles':>10}{'ours load s':>13}{'job json s':>12}{'convert s':>11}{'mitsuba s':>11}"
          f"{'ratio':>7}")
    for r in rows:
        print(f"{r['format']:<11}{r['triangles']:>10}{r['ours_load_s']:>13.3f}{r['ours_job_json_s']:>12.3f}"
              f"{r['ours_convert_s']:>11.3f}{r['mitsuba_load_s']:>11.3f}{r['ratio']:>7.2f}")
    print(f"wrote {write_json('import_speed', {'rows': rows, 'limit_ratio': 2.0})}")


if __name__ == "__main__":
    main()
