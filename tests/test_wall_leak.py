"""A gather disc cut by a wall counts no photon beyond the wall.

One floor quad runs under a black wall from a lit side to a dark side that no light can
reach (the scene is open: nothing sends light over the wall). Points on the dark floor
within the radius of the wall find the lit side's photons on the same plane, with the same
normal, arrived from above: only the disc's cut (the coverage rays, eye_pass.cl inside_cut)
keeps them out. Before it the dark floor near the wall was lit (here a mean of 0.03, 117
of 576 pixels above 1e-3; on `gap` 5.9x the reference there), and the adaptive sampler
called 23% of the paths visible. Two gaps were left, both closed now, and the dark floor is
exactly black:
- points within the cut's quantum of the wall's foot took every photon of the sectors whose
  two rays both met the wall there (a mean of 1.2e-4 of the lit floor, 1-2 pixels above
  1e-3, 4% of the paths visible);
- a wall that cut only the disc's rim between two rays (up to 1 - cos(pi / 8) of the radius
  deep) met no ray, and its photons counted (3e-9 of the lit floor with SPPM's smooth
  kernel, 1e-5 with vcm's uniform one): the rays now reach 1 / cos(pi / 8) of the radius.

Light tracing and bidirectional connections have no disc: nothing at all may cross. Their
shadow rays from the lit floor within the ray offset of the wall crossed it while rays
skipped every hit that near (geometry.cl, ray_eps): 2 pixels each, 4e-5 of mean. In two
rooms parted by a whole wall, bpt still lit 208 of 1024 pixels of the dark room: a
connection to a light vertex, or a shadow ray to a light sample, within the ray offset of
the wall's lit side stopped short of that point along the ray, beyond the wall (geometry.cl,
blocked_between)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from tests.conftest import image, render


def _wall_scene() -> dict:
    """Floor y = 0 over |x|, |z| < 10, a black wall x = 0 up to y = 10, a spot light on the
    +x side aimed at the floor next to the wall; the camera above the -x side looks at the
    dark floor up to the wall's foot."""
    return {
        "camera": {"position": [-0.6, 2.0, 0.0], "look_at": [-0.6, 0.0, 0.0], "up": [1, 0, 0], "fov": 40,
                   "resolution": [24, 24]},
        "materials": {"floor": {"type": "diffuse", "albedo": [0.5, 0.5, 0.5]},
                      "black": {"type": "diffuse", "albedo": [0.0, 0.0, 0.0]}},
        "shapes": [{"type": "quad", "corner": [-10, 0, -10], "edge1": [0, 0, 20], "edge2": [20, 0, 0],
                    "material": "floor"},
                   {"type": "quad", "corner": [0, 0, -10], "edge1": [0, 10, 0], "edge2": [0, 0, 20],
                    "material": "black"}],
        "lights": [{"type": "spot", "position": [0.5, 1.0, 0.0], "direction": [0, -1, 0], "cone_angle": 40.0,
                    "power": [10.0, 10.0, 10.0]}],
    }


def _two_rooms_scene() -> dict:
    """A 4 x 2 x 2 box parted at x = 2 by a whole wall; a lamp under the ceiling of the
    x > 2 room, against the wall (its light samples too may lie within the offset of it);
    the camera in the other room looks at the wall. Nothing can light it."""
    def quad(corner: list[float], edge1: list[float], edge2: list[float], **extra: object) -> dict:
        return {"type": "quad", "corner": corner, "edge1": edge1, "edge2": edge2, "material": "white", **extra}
    return {
        "camera": {"position": [0.15, 1.4, 1.0], "look_at": [2.0, 0.6, 1.0], "up": [0, 1, 0], "fov": 70,
                   "resolution": [32, 32]},
        "materials": {"white": {"type": "diffuse", "albedo": [0.7, 0.7, 0.7]}},
        "shapes": [quad([0, 0, 0], [0, 0, 2], [4, 0, 0]), quad([0, 2, 0], [4, 0, 0], [0, 0, 2]),
                   quad([0, 0, 0], [0, 2, 0], [4, 0, 0]), quad([0, 0, 2], [4, 0, 0], [0, 2, 0]),
                   quad([0, 0, 0], [0, 0, 2], [0, 2, 0]), quad([4, 0, 0], [0, 2, 0], [0, 0, 2]),
                   quad([2, 0, 0], [0, 2, 0], [0, 0, 2]),
                   quad([2.0, 1.99, 0.8], [0.4, 0, 0], [0, 0, 0.4], emission=[40, 40, 40])],
        "lights": [],
    }


@pytest.mark.parametrize("scene, radius", [(_wall_scene, 0.4), (_two_rooms_scene, 0.1)])
@pytest.mark.parametrize("method, settings", [("sppm", {}), ("sppm", {"sampler": "adaptive"}),
                                              ("sppm", {"direct": "nee"}), ("vcm", {})])
def test_no_light_through_the_wall(make_engine, tmp_path: Path, scene, radius: float, method: str,
                                   settings: dict) -> None:
    """With vcm, the same for merging: its light vertices on the lit floor beyond the wall."""
    path = tmp_path / "wall.json"
    path.write_text(json.dumps(scene()))
    # radius 0.4: the points within 0.4 of the wall (about the right half of the view)
    # reach the lit floor under it; in the two rooms, the walls' and floor's points by the wall
    eng = make_engine(path, photons_per_pass=1 << 13, seed=12, initial_radius=radius, method=method, **settings)
    state = render(eng, 4)
    img = image(eng, state)
    assert img.max() == 0.0, ((img > 0).sum(), img.mean())
    if settings.get("sampler") == "adaptive":  # no photon path is visible: it would have to reach the dark side
        assert state.counters["visible"] == 0 and state.counters["draws"] > 0, state.counters


@pytest.mark.parametrize("scene", [_wall_scene, _two_rooms_scene])
@pytest.mark.parametrize("method", ["bpt", "lt"])
def test_no_connection_through_the_wall(make_engine, tmp_path: Path, method: str, scene) -> None:
    path = tmp_path / "wall.json"
    path.write_text(json.dumps(scene()))
    eng = make_engine(path, photons_per_pass=1 << 13, seed=12, method=method)
    img = image(eng, render(eng, 4))
    assert img.max() == 0.0, ((img > 0).sum(), img.max())
