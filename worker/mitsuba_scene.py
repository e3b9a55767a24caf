"""Mitsuba 3 XML scenes converted to our scene JSON (the subset our model holds).

The conversion is element by element (docs/scenes.md, "Mitsuba 3 XML"); anything outside the
subset that would change the image is a `SceneError` naming the element and its line, never
a silent change; what changes nothing here is accepted and reported as a note ("ignored:
..."). Meshes are inlined with their `to_world` applied (our meshes have no transform), so
the JSON is self-contained. Files the scene names (meshes, spectra, includes) are found as
Mitsuba's file resolver finds them (`Converter.start`) and must lie inside `root`.

XML is read with expat, which reports the line of every element (ElementTree does not).
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, overload
from xml.parsers import expat

import numpy as np

from worker import spectra
from worker.images import IMAGE_SUFFIXES, Pixels
from worker.meshes import MeshData, MeshError
from worker.metals import METALS
from worker.scene import (
    MAX_INCLUDE_DEPTH,
    MAX_TRIANGLES,
    MAX_XML_DEPTH,
    ROTATION_TOLERANCE,
    LoadBudget,
    Scene,
    SceneError,
    collector_paused,
    parse_scene,
    read_mesh,
    read_texture,
)
from worker.serialized import header_counts, read_serialized
from worker.spectra import Kind

# Named indices of refraction, as Mitsuba 3's dielectric documentation lists them.
NAMED_IOR = {
    "vacuum": 1.0, "helium": 1.000036, "hydrogen": 1.000132, "air": 1.000277, "carbon dioxide": 1.00045,
    "water": 1.3330, "acetone": 1.36, "ethanol": 1.361, "carbon tetrachloride": 1.461, "glycerol": 1.4729,
    "benzene": 1.501, "silicone oil": 1.52045, "bromine": 1.661, "water ice": 1.31, "fused quartz": 1.458,
    "pyrex": 1.470, "acrylic glass": 1.49, "polypropylene": 1.49, "bk7": 1.5046, "sodium chloride": 1.544,
    "amber": 1.55, "pet": 1.5750, "diamond": 2.419,
}
# Mitsuba's plugins that pass light through: refused inside `twosided`, as Mitsuba refuses them there.
TRANSMISSIVE = {"dielectric", "thindielectric", "roughdielectric", "mask"}
DISK_SEGMENTS = 256  # a disk becomes a fan of this many triangles (area within 1e-4)
# Mitsuba's cube: the corners of each face in its order, which its texture coordinates follow.
CUBE_FACES = (((1, -1, -1), (1, -1, 1), (-1, -1, 1), (-1, -1, -1)),  # y = -1
              ((1, 1, -1), (-1, 1, -1), (-1, 1, 1), (1, 1, 1)),  # y = 1
              ((1, -1, -1), (1, 1, -1), (1, 1, 1), (1, -1, 1)),  # x = 1
              ((1, -1, 1), (1, 1, 1), (-1, 1, 1), (-1, -1, 1)),  # z = 1
              ((-1, -1, 1), (-1, 1, 1), (-1, 1, -1), (-1, -1, -1)),  # x = -1
              ((1, 1, -1), (1, -1, -1), (-1, -1, -1), (-1, 1, -1)))  # z = -1
CYLINDER_SEGMENTS = 256  # a cylinder becomes a tube of 2x this many triangles (area within 1e-4)
NORMALS_CHUNK = 1 << 14  # triangles per step of _vertex_normals: its temporaries stay in cache, not in fresh pages
# Settings of the renderer, not of the scene: our jobs take them from their own settings.
RENDER_SETTING_TAGS = {"integrator", "sampler", "rfilter"}
# What the model cannot hold, refused by name wherever it appears.
UNSUPPORTED = {"medium": "participating media are not supported",
               "phase": "participating media (phase functions) are not supported",
               "volume": "participating media (volume grids) are not supported"}
PROPERTY_TAGS = {"float", "integer", "boolean", "string", "rgb", "spectrum", "point", "vector", "transform", "ref"}


# ------------------------------------------------------------------------ XML reading
@dataclass
class Node:
    tag: str
    attrs: dict[str, str]
    line: int
    file: Path
    children: list[Node] = field(default_factory=list)

    def where(self) -> str:
        kind = f' type="{self.attrs["type"]}"' if "type" in self.attrs else ""
        name = f' name="{self.attrs["name"]}"' if "name" in self.attrs and "type" not in self.attrs else ""
        return f"line {self.line}: <{self.tag}{kind}{name}>"


def _error(node: Node, message: str) -> SceneError:
    return SceneError(node.file.name, f"{node.where()}: {message}")


def _read_xml(path: Path, budget: LoadBudget, field: str = "", at: str = "") -> Node:
    """The element tree of an XML file, each element with its line number, read within the
    budget (`field` and `at` name the element that includes it) and at most MAX_XML_DEPTH deep."""
    try:
        data = budget.read(path, "scene files", field or path.name, at)
    except FileNotFoundError:
        raise SceneError("", f"scene file {str(path)!r} not found") from None
    except OSError as exc:
        raise SceneError("", f"cannot read scene file {str(path)!r}: {exc.strerror or exc}") from None
    parser = expat.ParserCreate()
    stack: list[Node] = []
    roots: list[Node] = []

    def start(tag: str, attrs: dict[str, str]) -> None:
        node = Node(tag, dict(attrs), parser.CurrentLineNumber, path)
        budget.take("XML elements", 1, path.name, node.where())
        if len(stack) >= MAX_XML_DEPTH:
            raise _error(node, f"XML nested deeper than {MAX_XML_DEPTH} elements")
        (stack[-1].children if stack else roots).append(node)
        stack.append(node)

    def end(tag: str) -> None:
        stack.pop()

    def text(data: str) -> None:
        if data.strip():
            raise SceneError(path.name, f"line {parser.CurrentLineNumber}: unexpected text {data.strip()[:40]!r}")

    parser.StartElementHandler, parser.EndElementHandler, parser.CharacterDataHandler = start, end, text
    try:
        parser.Parse(data, True)
    except expat.ExpatError as exc:
        raise SceneError(path.name, f"line {exc.lineno}: malformed XML: {expat.ErrorString(exc.code)}") from None
    return roots[0]


# ----------------------------------------------------------------------- values
def _floats(node: Node, text: str, count: int | None = None) -> list[float]:
    try:
        values = [float(x) for x in re.split(r"[,\s]+", text.strip()) if x]
    except ValueError:
        raise _error(node, f"not a list of numbers: {text!r}") from None
    if not all(math.isfinite(v) for v in values):
        raise _error(node, f"non-finite number in {text!r}")
    if count is not None and len(values) != count:
        raise _error(node, f"expected {count} numbers, got {len(values)}")
    return values


def _xyz(node: Node, default: float) -> np.ndarray:
    """A vector given as value="x, y, z" or as x/y/z attributes (missing ones default)."""
    if "value" in node.attrs:
        values = _floats(node, node.attrs["value"])
        if len(values) == 1:
            values *= 3
        if len(values) != 3:
            raise _error(node, "expected one or three numbers")
        return np.array(values)
    return np.array([float(_floats(node, node.attrs.get(k, str(default)), 1)[0]) for k in "xyz"])


def _rotation(axis: np.ndarray, degrees: float) -> np.ndarray:
    """Rotation about `axis` (right-handed, degrees), as a 4x4 matrix (Rodrigues)."""
    a = axis / np.linalg.norm(axis)  # removes the rounding of a unit axis written in decimals
    th = math.radians(degrees)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    m = np.eye(4)
    m[:3, :3] = np.eye(3) + math.sin(th) * k + (1 - math.cos(th)) * (k @ k)
    return m


def look_at(origin: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """Mitsuba's lookat: columns (left, up, dir, origin); the camera looks along local +z."""
    d = target - origin
    d = d / np.linalg.norm(d)
    left = np.cross(up, d)
    left = left / np.linalg.norm(left)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = left, np.cross(d, left), d, origin
    return m


def _transform_op(node: Node) -> np.ndarray:
    """One child of <transform> as a 4x4 matrix."""
    a = node.attrs
    if node.tag == "translate":
        m = np.eye(4)
        m[:3, 3] = _xyz(node, 0.0)
        return m
    if node.tag == "scale":
        return np.diag([*_xyz(node, 1.0), 1.0])
    if node.tag == "rotate":
        axis = _xyz(node, 0.0)
        if "angle" not in a:
            raise _error(node, "rotate needs an axis and an angle")
        if abs(np.linalg.norm(axis) - 1.0) > 1e-5:  # Mitsuba uses the axis as given: no rotation then
            raise _error(node, f"the rotation axis must have unit length (has {np.linalg.norm(axis):g})")
        return _rotation(axis, _floats(node, a["angle"], 1)[0])
    if node.tag == "matrix":
        values = _floats(node, a.get("value", ""))
        if len(values) == 9:
            m = np.eye(4)
            m[:3, :3] = np.reshape(values, (3, 3))
            return m
        if len(values) != 16:
            raise _error(node, "a matrix has 9 or 16 numbers (row by row)")
        return np.reshape(values, (4, 4))
    if node.tag == "lookat":
        if not {"origin", "target"} <= a.keys():
            raise _error(node, "lookat needs origin and target")
        o, t = (np.array(_floats(node, a[k], 3)) for k in ("origin", "target"))
        u = np.array(_floats(node, a["up"], 3)) if "up" in a else _some_up(t - o)
        if not np.linalg.norm(t - o) > 0 or not np.linalg.norm(np.cross(u, t - o)) > 0:
            raise _error(node, "lookat target equals origin or up is parallel to the view")
        return look_at(o, t, u)
    raise _error(node, "unknown transform operation (have: translate, rotate, scale, matrix, lookat)")


def _some_up(forward: np.ndarray) -> np.ndarray:
    """Mitsuba's `up` where a lookat gives none: the first tangent of the orthonormal basis
    about the view direction (Duff et al. 2017); a zero direction is refused by the caller."""
    length = float(np.linalg.norm(forward))
    if not length > 0:
        return np.zeros(3)
    x, y, z = forward / length
    sign = math.copysign(1.0, z)
    a = -1.0 / (sign + z)
    return np.array([1.0 + sign * x * x * a, sign * x * y * a, -sign * x])


def to_world_matrix(node: Node) -> np.ndarray:
    """Compose a <transform>: each operation applies after the ones before it (M = op M)."""
    m = np.eye(4)
    for child in node.children:
        m = _transform_op(child) @ m
    if not np.all(np.isfinite(m)):
        raise _error(node, "non-finite transform")
    return m


def _times(rows: np.ndarray, a: np.ndarray) -> np.ndarray:
    """rows @ a for (n, 3) rows and a 3 x 3 matrix, computed in this thread: matmul hands so
    thin a product to BLAS, whose threads stall while the machine's cores are busy."""
    return np.einsum("ij,jk->ik", rows, a)


def _apply(m: np.ndarray, points: np.ndarray) -> np.ndarray:
    return _times(points, m[:3, :3].T) + m[:3, 3]


# ----------------------------------------------------------------------- properties
class Props:
    """The properties of one plugin element; each must be used (or ignored with a note), or it is an error."""

    def __init__(self, owner: Node, conv: Converter) -> None:
        self.owner = owner
        self.conv = conv
        self.values: dict[str, Node] = {}
        self.objects: list[Node] = []
        for child in owner.children:
            if child.tag in PROPERTY_TAGS and "name" in child.attrs and child.tag != "ref":
                if child.attrs["name"] in self.values:
                    raise _error(child, f"property {child.attrs['name']!r} given twice")
                self.values[child.attrs["name"]] = child
            else:
                self.objects.append(child)

    def _take(self, name: str, tags: set[str]) -> Node | None:
        node = self.values.pop(name, None)
        if node is not None and node.tag not in tags:
            raise _error(node, f"{name} must be one of <{'>, <'.join(sorted(tags))}>")
        return node

    @overload
    def number(self, name: str) -> float | None: ...
    @overload
    def number(self, name: str, default: float) -> float: ...

    def number(self, name: str, default: float | None = None) -> float | None:
        node = self._take(name, {"float", "integer"})
        return default if node is None else _floats(node, node.attrs.get("value", ""), 1)[0]

    def integer(self, name: str, default: int) -> int:
        node = self._take(name, {"integer"})
        if node is None:
            return default
        try:
            return int(node.attrs.get("value", ""))
        except ValueError:
            raise _error(node, "not an integer") from None

    def boolean(self, name: str, default: bool) -> bool:
        node = self._take(name, {"boolean"})
        if node is None:
            return default
        value = node.attrs.get("value", "").lower()
        if value not in ("true", "false"):
            raise _error(node, "a boolean is true or false")
        return value == "true"

    @overload
    def string(self, name: str) -> str | None: ...
    @overload
    def string(self, name: str, default: str) -> str: ...

    def string(self, name: str, default: str | None = None) -> str | None:
        node = self._take(name, {"string"})
        return default if node is None else node.attrs.get("value", "")

    def ignore(self, name: str, why: str) -> None:
        """Accept a property that does not change our image, with a note saying so."""
        node = self.values.pop(name, None)
        if node is not None:
            self.conv.note(self.owner, node, name, why)

    def color(self, name: str, default: float, kind: Kind = "reflectance") -> tuple[float, float, float]:
        """rgb, float, or a spectrum (converted to linear sRGB as `kind`, worker/spectra.py);
        textures are outside the subset."""
        node = self.values.get(name)
        if node is None:
            for obj in self.objects:
                if obj.attrs.get("name") == name and obj.tag in ("texture", "ref"):
                    target = self.conv.deref(obj) if obj.tag == "ref" else obj
                    raise _error(obj, f"texture plugin {target.attrs.get('type', '')!r} is not supported "
                                      "(constant colours only)")
            return (default,) * 3
        node = self._take(name, {"rgb", "spectrum", "float"})
        assert node is not None, "taken just after it was found"
        if node.tag == "spectrum":
            return self.conv.spectrum(node, kind)
        values = _floats(node, node.attrs.get("value", ""))
        if len(values) == 1:
            values *= 3
        if len(values) != 3:
            raise _error(node, "expected one or three values")
        return tuple(values)  # type: ignore[return-value]

    def vector(self, name: str, tag: str) -> np.ndarray | None:
        node = self._take(name, {tag})
        return None if node is None else _xyz(node, 0.0)

    def transform(self, name: str = "to_world") -> np.ndarray:
        node = self._take(name, {"transform"})
        return np.eye(4) if node is None else to_world_matrix(node)

    def node_of(self, name: str) -> Node:
        return self.values.get(name, self.owner)

    def done(self) -> None:
        """Refuse properties the conversion did not use."""
        if self.values:
            name, node = next(iter(self.values.items()))
            raise _error(node, f"property {name!r} is not supported on <{self.owner.tag} "
                               f"type=\"{self.owner.attrs.get('type', '')}\">")


def _named_metal(node: Node, name: str, p: Props) -> tuple[list[float], list[float]]:
    """rgb eta and k of Mitsuba's named conductor `name` (its <string> is `node`) from
    worker/metals.py; an error for a name it does not hold, or with eta or k given too."""
    for given in ("eta", "k"):
        if given in p.values:
            raise _error(p.values[given], f"give material or {given}, not both (Mitsuba refuses both too)")
    if name not in METALS:
        raise _error(node, f"named conductor material {name!r} is not held here (have: {', '.join(METALS)}); "
                           "give eta and k (rgb, float or spectrum) instead")
    return list(METALS[name].eta), list(METALS[name].k)


# ------------------------------------------------------------------------ conversion
@dataclass
class Converter:
    root: Path
    params: dict[str, str]
    materials: dict[str, dict] = field(default_factory=dict)
    textures: dict[str, dict] = field(default_factory=dict)  # bitmaps (an envmap's too) and checkerboards
    shapes: list[dict] = field(default_factory=list)
    lights: list[dict] = field(default_factory=list)
    camera: dict | None = None
    budget: LoadBudget = field(default_factory=LoadBudget)  # of the whole load, includes and meshes too
    triangles: int = 0  # so far, every shape's, against MAX_TRIANGLES before the JSON grows past it
    origin: dict[str, Node] = field(default_factory=dict)  # our JSON path -> XML element
    named: dict[str, Node] = field(default_factory=dict)  # id -> element, for <ref id>
    referenced: set[str] = field(default_factory=set)  # ids some <ref> used
    notes: list[str] = field(default_factory=list)  # "ignored: ..." lines, each said once
    noted: set[tuple[str, str, str]] = field(default_factory=set)
    # Folders searched for a file named while the XML is read (includes), first to last.
    search: list[Path] = field(default_factory=list)
    # Folders searched for the files plugins name (meshes, spectra): the main file's <path>s,
    # the last one first, then the main file's folder.
    file_search: list[Path] = field(default_factory=list)

    # -------------------------------------------------------------- notes and refs
    def note(self, owner: Node, node: Node, name: str, why: str) -> None:
        """Record once per kind of element and property that the property is ignored, and why."""
        key = (owner.tag, owner.attrs.get("type", ""), name)
        if key not in self.noted:
            self.noted.add(key)
            self.notes.append(f"ignored: {node.file.name} {owner.where()}: {name} ({why})")

    def deref(self, node: Node) -> Node:
        """The element a <ref id> names (defined before it)."""
        if set(node.attrs) - {"id", "name"}:
            raise _error(node, "a ref takes an id (and a name)")
        target = self.named.get(node.attrs.get("id", ""))
        if target is None:
            raise _error(node, f"no object with id {node.attrs.get('id', '')!r} defined before this reference")
        self.referenced.add(node.attrs["id"])
        return target

    def _note_id(self, node: Node) -> None:
        """An id on a sensor, shape or light names it for Mitsuba's API only: noted."""
        if "id" in node.attrs:
            self.note(node, node, "id", "names the object in Mitsuba's API only")

    def define(self, node: Node) -> None:
        """Remember an element by its id for later references."""
        name = node.attrs.get("id")
        if name is not None:
            if name in self.named:
                raise _error(node, f"id {name!r} defined twice")
            self.named[name] = node

    # -------------------------------------------------------------- scene walk
    def substitute(self, top: Node) -> None:
        """Replace $name in every attribute of top and its descendants (Mitsuba's parameters),
        walking the tree with a list rather than the call stack."""
        pending = [top]
        while pending:
            node = pending.pop()

            def repl(match: re.Match, node: Node = node) -> str:
                if match.group(1) not in self.params:
                    raise _error(node, f"undefined parameter ${match.group(1)}")
                return self.params[match.group(1)]

            node.attrs = {k: re.sub(r"\$(\w+)", repl, v) for k, v in node.attrs.items()}
            pending.extend(node.children)

    def _default(self, node: Node) -> None:
        if "name" not in node.attrs or "value" not in node.attrs:
            raise _error(node, "a default needs name and value")
        self.params.setdefault(node.attrs["name"], node.attrs["value"])

    def _path(self, node: Node) -> Path:
        """A <path value> folder: relative to the file that holds it, inside the root."""
        self.substitute(node)
        if set(node.attrs) != {"value"}:
            raise _error(node, "a path takes exactly a value")
        try:
            folder = (node.file.parent / node.attrs["value"]).resolve()
        except (OSError, ValueError) as exc:
            raise _error(node, f"folder cannot be used: {getattr(exc, 'strerror', None) or exc}") from None
        if not folder.is_relative_to(self.root):
            raise _error(node, f"{node.attrs['value']!r} leaves the scene's directory")
        return folder

    def start(self, top: Node) -> None:
        """Set up Mitsuba's file resolver for the main file `top`: while its XML is read, its
        folder and then the <path>s read so far (each searched before the earlier ones); for
        plugins' files, every <path> of the main file, wherever it stands, then its folder
        (Mitsuba loads those files once the whole scene is read; an included file's <path>s
        only apply while it is read)."""
        self.search = [top.file.parent]
        self.file_search = [top.file.parent]
        for child in top.children:
            if child.tag == "default":
                self._default(child)
            elif child.tag == "path":
                self.file_search.insert(0, self._path(child))

    def scene(self, node: Node, depth: int = 0) -> None:
        if node.tag != "scene":
            raise _error(node, "the root element must be <scene>")
        version = node.attrs.get("version", "")
        if not re.fullmatch(r"[23]\.\d+(\.\d+)?", version):
            raise _error(node, f"version {version!r}: only Mitsuba 3 (or 2) scenes are read")
        outer = list(self.search)
        if depth > 0:  # an included file's folder is searched first while it is read
            self.search.insert(0, node.file.parent)
        for child in node.children:
            if child.tag == "default":
                self._default(child)
                continue
            self.substitute(child)
            if child.tag == "path":
                self.search.insert(0, self._path(child))
            elif child.tag == "include":
                self.include(child, depth)
            elif child.tag == "sensor":
                self.sensor(child)
            elif child.tag == "bsdf":
                self.bsdf(child)
            elif child.tag == "shape" and child.attrs.get("type") == "shapegroup":
                if "id" not in child.attrs:
                    raise _error(child, "a shapegroup needs an id (instances refer to it)")
                self.define(child)
            elif child.tag == "shape":
                self.shape(child)
            elif child.tag == "emitter" and child.attrs.get("type") == "area" and "id" in child.attrs:
                self.define(child)  # converted where a shape refers to it
            elif child.tag == "emitter":
                self.light(child)
            elif child.tag == "texture" and "id" in child.attrs:
                self.define(child)  # converted where a bsdf refers to it
            elif child.tag in RENDER_SETTING_TAGS:
                self.note(child, child, f"<{child.tag}>", "render settings belong to the job")
            elif child.tag in UNSUPPORTED:
                raise _error(child, UNSUPPORTED[child.tag])
            else:
                raise _error(child, f"<{child.tag}> is not supported at scene level")
        if depth > 0:
            self.search = outer

    def _find(self, node: Node, name: str, folders: list[Path]) -> Path:
        """The first of folder/name (for each folder in order) that is a file inside root."""
        shown = name if len(name) <= 80 else f"{name[:80]}..."
        left = False
        try:
            for folder in folders:
                path = (folder / name).resolve()
                if not path.is_relative_to(self.root):
                    left = True
                elif path.is_file():
                    return path
        except (OSError, ValueError) as exc:  # a name the file system refuses (too long in bytes, NUL)
            raise _error(node, f"file {shown!r} cannot be opened: {getattr(exc, 'strerror', None) or exc}") from None
        if left:
            raise _error(node, f"{shown!r} leaves the scene's directory")
        raise _error(node, f"file {shown!r} not found")

    def resolve(self, node: Node, name: str) -> Path:
        """A file a plugin names (a mesh, a spectrum), found as Mitsuba finds it (`file_search`);
        failing that, beside the XML file that names it (our own extension: Mitsuba would not
        load such a scene, so no scene it loads reads another file here)."""
        return self._find(node, name, [*self.file_search, node.file.parent])

    def include(self, node: Node, depth: int) -> None:
        if depth >= MAX_INCLUDE_DEPTH:
            raise _error(node, f"includes nested deeper than {MAX_INCLUDE_DEPTH}")
        if set(node.attrs) != {"filename"}:
            raise _error(node, "an include takes exactly a filename")
        path = self._find(node, node.attrs["filename"], self.search)
        if path.suffix.lower() != ".xml":
            raise _error(node, "only XML files can be included")
        self.scene(_read_xml(path, self.budget, node.file.name, node.where()), depth + 1)

    # -------------------------------------------------------------- spectra
    def spectrum(self, node: Node, kind: Kind) -> tuple[float, float, float]:
        """A <spectrum> as linear sRGB (worker/spectra.py): `value` (one number, or
        wavelength:value pairs), `filename` (a .spd file), or a plugin (`blackbody`, `uniform`)."""
        plugin = node.attrs.get("type")
        try:
            if plugin is not None:
                return self._spectrum_plugin(node, plugin, kind)
            if "filename" in node.attrs:
                path = self.resolve(node, node.attrs["filename"])
                data = self.budget.read(path, "scene files", node.file.name, node.where())
                w, v = spectra.parse_spd(data.decode("utf-8", errors="replace"))
                return spectra.sampled_to_rgb(w, v, kind)
            text = node.attrs.get("value", "")
            if ":" not in text:
                return spectra.uniform_to_rgb(_floats(node, text, 1)[0], kind)
            pairs = [item.split(":") for item in re.split(r"\s*,\s*", text.strip()) if item]
            if not all(len(pair) == 2 for pair in pairs):
                raise ValueError("expected wavelength:value pairs separated by commas")
            w, v = spectra.check_samples([float(a) for a, _ in pairs], [float(b) for _, b in pairs])
            return spectra.sampled_to_rgb(w, v, kind)
        except ValueError as exc:
            raise _error(node, str(exc)) from None

    def _spectrum_plugin(self, node: Node, plugin: str, kind: Kind) -> tuple[float, float, float]:
        p = Props(node, self)
        if plugin == "blackbody":
            if kind != "emission":
                raise _error(node, "a blackbody spectrum is an emission (in an emitter)")
            out = spectra.blackbody_to_rgb(p.number("temperature", math.nan) or math.nan)
        elif plugin == "uniform":
            out = spectra.uniform_to_rgb(p.number("value", 1.0) or 0.0, kind)
        else:  # Mitsuba's RGB variants cannot evaluate `regular` and `irregular` either
            raise _error(node, f"unknown spectrum plugin {plugin!r} (have: blackbody, uniform; "
                               "or wavelength:value pairs in `value`)")
        for obj in p.objects:
            raise _error(obj, f"<{obj.tag}> is not supported in a spectrum")
        p.done()
        return out

    # -------------------------------------------------------------- sensor
    def sensor(self, node: Node) -> None:
        if self.camera is not None:
            raise _error(node, "more than one sensor")
        kind = node.attrs.get("type")
        if kind not in ("perspective", "thinlens"):
            raise _error(node, f"unknown sensor plugin {kind!r} (have: perspective, thinlens)")
        self._note_id(node)
        p = Props(node, self)
        m = p.transform()
        width, height = 768, 576
        for obj in p.objects:
            if obj.tag == "film":
                width, height = self.film(obj)
            elif obj.tag in RENDER_SETTING_TAGS:
                self.note(obj, obj, f"<{obj.tag}>", "render settings belong to the job")
            elif obj.tag in UNSUPPORTED:
                raise _error(obj, UNSUPPORTED[obj.tag])
            else:
                raise _error(obj, f"<{obj.tag}> is not supported in a sensor")
        # Field of view: `fov` along `fov_axis`, or a `focal_length` on 36 x 24 mm film (the
        # diagonal's; Mitsuba's default is 50 mm), turned into our vertical angle.
        if "fov" in p.values:
            if "focal_length" in p.values:
                raise _error(p.values["focal_length"], "give fov or focal_length, not both")
            given_fov, axis = p.number("fov"), p.string("fov_axis", "x")
            assert given_fov is not None, "fov is among the values"
            fov = given_fov
        else:
            text = p.string("focal_length", "50mm")
            try:
                focal = float(text.removesuffix("mm"))
            except ValueError:
                raise _error(p.node_of("focal_length"), f"focal_length {text!r} is not in mm") from None
            if not focal > 0:
                raise _error(p.node_of("focal_length"), "focal_length must be positive")
            fov, axis = math.degrees(2 * math.atan(math.hypot(36.0, 24.0) / (2 * focal))), "diagonal"
        if not 0 < fov < 180:
            raise _error(p.node_of("fov"), "fov must lie in (0, 180) degrees")
        tan = math.tan(math.radians(fov) / 2)
        scale = {"x": height / width, "y": 1.0, "diagonal": height / math.hypot(width, height),
                 "smaller": height / width if width < height else 1.0,
                 "larger": height / width if width > height else 1.0}
        if axis not in scale:
            raise _error(p.node_of("fov_axis"), f"fov_axis {axis!r} (have: {', '.join(scale)})")
        fov_y = math.degrees(2 * math.atan(tan * scale[axis]))
        near = p.number("near_clip", 0.01)
        p.ignore("far_clip", "not applied: everything in front of the camera is seen")
        for name in ("shutter_open", "shutter_close"):
            p.ignore(name, "nothing in the scene moves")
        p.ignore("srf", "spectral response: our images are linear sRGB")
        cam: dict[str, Any] = {"fov": fov_y, "resolution": [width, height], "near_clip": near}
        if kind == "perspective":
            p.ignore("focus_distance", "a pinhole camera has every depth in focus")
        else:
            aperture, focus = p.number("aperture_radius"), p.number("focus_distance")
            if aperture is None or focus is None:
                raise _error(node, "a thinlens sensor needs aperture_radius and focus_distance")
            cam["aperture_radius"], cam["focus_distance"] = aperture, focus
        p.done()

        # The camera frame: Mitsuba looks along local +z with local +x to the image's left.
        r = m[:3, :3]
        if not np.allclose(r.T @ r, np.eye(3), atol=1e-6) or np.linalg.det(r) < 0:
            raise _error(node, "the sensor's to_world must be a rotation and translation (no scale, shear or mirror)")
        origin, forward, up = m[:3, 3], r[:, 2], r[:, 1]
        cam.update(position=origin.tolist(), look_at=(origin + forward).tolist(), up=up.tolist())
        self.camera = cam
        self.origin["camera"] = node

    def film(self, node: Node) -> tuple[int, int]:
        if node.attrs.get("type") != "hdrfilm":
            raise _error(node, "only hdrfilm is supported")
        p = Props(node, self)
        size = p.integer("width", 768), p.integer("height", 576)
        for name in ("pixel_format", "component_format", "file_format", "banner"):
            p.ignore(name, "output encoding: the job chooses its own")
        for name in ("high_quality_edges", "sample_border", "compensate"):
            p.ignore(name, "reconstruction detail: our pixels are box-filtered")
        for obj in p.objects:
            if obj.tag != "rfilter":
                raise _error(obj, f"<{obj.tag}> is not supported in a film")
            self.note(obj, obj, "<rfilter>", "our pixels are box-filtered")
        p.done()
        return size

    # -------------------------------------------------------------- materials
    def bsdf(self, node: Node) -> str:
        """Convert a <bsdf> (top-level with an id, or nested in a shape); returns our name."""
        name = node.attrs.get("id") or f"{node.file.stem}-line{node.line}"
        if self.origin.get(f"materials.{name}") is node:  # a shapegroup's, met again through another instance
            return name
        if name in self.materials:
            raise _error(node, f"bsdf id {name!r} defined twice")
        self.materials[name] = self.material(node)
        self.origin[f"materials.{name}"] = node
        self.define(node)
        return name

    def material(self, node: Node) -> dict:
        kind = node.attrs.get("type")
        p = Props(node, self)
        if kind == "twosided":  # our opaque surfaces reflect on both sides already
            inner = [self.deref(o) if o.tag == "ref" else o for o in p.objects]
            if len(inner) != 1 or inner[0].tag != "bsdf":
                raise _error(node, "twosided takes exactly one nested bsdf (different sides are not supported)")
            if inner[0].attrs.get("type") in TRANSMISSIVE:
                raise _error(p.objects[0], "twosided takes an opaque bsdf (Mitsuba refuses one that transmits)")
            p.done()
            if p.objects[0].tag == "ref":
                return dict(self.materials[inner[0].attrs["id"]])
            return self.material(inner[0])
        convert: dict[str, Callable[[Props], dict]] = {
            "diffuse": self._diffuse, "conductor": self._conductor, "roughconductor": self._roughconductor,
            "dielectric": self._dielectric, "roughdielectric": self._roughdielectric,
            "thindielectric": self._thindielectric, "plastic": self._plastic,
            "roughplastic": self._roughplastic,
        }
        if kind == "mask":
            return self._mask(node, p)
        if kind not in convert:
            raise _error(node, f"unknown bsdf plugin {kind!r} (have: {', '.join(['twosided', *convert])})")
        out = convert[kind](p)
        for obj in p.objects:
            target = self.deref(obj) if obj.tag == "ref" else obj
            if target.tag == "texture":
                raise _error(obj, f"a texture for {obj.attrs.get('name', '')!r} is not supported on a {kind} bsdf")
            raise _error(obj, f"<{obj.tag}> is not supported in a {kind} bsdf")
        p.done()
        return out

    def _mask(self, node: Node, p: Props) -> dict:
        """Mitsuba's mask: its one nested bsdf, with its `opacity` (a float, a colour's channel
        mean, or a texture; 0.5 by default, as Mitsuba's)."""
        opacity: float | dict | None = self._texture_of(p, "opacity")
        if opacity is None:
            where = p.node_of("opacity")
            opacity = sum(p.color("opacity", 0.5)) / 3.0
            if not 0.0 <= opacity <= 1.0:
                raise _error(where, "opacity must lie in [0, 1]")
        inner = [self.deref(o) if o.tag == "ref" else o for o in p.objects]
        if len(inner) != 1 or inner[0].tag != "bsdf":
            raise _error(node, "mask takes exactly one nested bsdf")
        p.done()
        nested = dict(self.materials[inner[0].attrs["id"]]) if p.objects[0].tag == "ref" else self.material(inner[0])
        if nested.get("opacity", 1.0) != 1.0:
            raise _error(inner[0], "a mask inside a mask is not supported")
        return {**nested, "opacity": opacity}

    def _albedo(self, p: Props, name: str, default: float) -> list[float] | dict:
        """A colour in [0, 1] (rgb, float or spectrum) or a texture (a reference to it)."""
        texture = self._texture_of(p, name)
        if texture is not None:
            return texture
        rgb = p.color(name, default)
        if not all(0.0 <= c <= 1.0 for c in rgb):
            raise _error(p.node_of(name), f"{name} must lie in [0, 1]")
        return list(rgb)

    # -------------------------------------------------------------- textures
    def _texture_of(self, p: Props, name: str) -> dict | None:
        """Property `name` of p given as a texture (<texture name> or <ref name id>): taken
        from p's objects, converted, and returned as our reference to it; None if it is not one."""
        for obj in p.objects:
            if obj.attrs.get("name") == name and obj.tag in ("texture", "ref"):
                if name in p.values:
                    raise _error(obj, f"property {name!r} given twice")
                p.objects.remove(obj)
                return {"texture": self.texture(obj)}
        return None

    def texture(self, obj: Node) -> str:
        """Convert a <texture> (nested, or top-level and referenced); returns our name."""
        node = self.deref(obj) if obj.tag == "ref" else obj
        if node.tag != "texture":
            raise _error(obj, f"{obj.attrs.get('id')!r} is not a texture")
        name = node.attrs.get("id") or f"{node.file.stem}-line{node.line}"
        if self.origin.get(f"textures.{name}") is node:  # met again through another reference
            return name
        kind = node.attrs.get("type")
        p = Props(node, self)
        # Mitsuba's to_uv is a 4x4 transform applied to (u, v, 0, 1).
        m = p.transform("to_uv")
        if not np.allclose(m[3], [0.0, 0.0, 0.0, 1.0]):
            raise _error(p.node_of("to_uv"), "a projective to_uv is not supported")
        to_uv = np.array([[m[0, 0], m[0, 1], m[0, 3]], [m[1, 0], m[1, 1], m[1, 3]]])
        if kind == "bitmap":
            out = self._bitmap(p, node)
        elif kind == "checkerboard":
            colors = [p.color(c, d) for c, d in (("color0", 0.4), ("color1", 0.2))]
            for c, rgb in zip(("color0", "color1"), colors, strict=True):
                if not all(0.0 <= x <= 1.0 for x in rgb):
                    raise _error(p.node_of(c), f"{c} must lie in [0, 1]")
            to_uv = 2.0 * to_uv  # Mitsuba's cells are half a unit of (u, v), ours one
            out = {"type": "checkerboard", "color0": list(colors[0]), "color1": list(colors[1])}
        else:
            raise _error(node, f"unknown texture plugin {kind!r} (have: bitmap, checkerboard)")
        for inner in p.objects:
            raise _error(inner, f"<{inner.tag}> is not supported in a texture")
        p.done()
        out["to_uv"] = to_uv.tolist()
        self.textures[name] = out
        self.origin[f"textures.{name}"] = node
        return name

    def _bitmap(self, p: Props, node: Node) -> dict:
        """A bitmap's image, read now (found as meshes are) and carried inline."""
        pixels = self._image(p, node, "a bitmap")
        filter_type, wrap = p.string("filter_type", "bilinear"), p.string("wrap_mode", "repeat")
        if filter_type not in ("bilinear", "nearest"):
            raise _error(p.node_of("filter_type"), "filter_type must be bilinear or nearest")
        if wrap not in ("repeat", "mirror", "clamp"):
            raise _error(p.node_of("wrap_mode"), "wrap_mode must be repeat, mirror or clamp")
        p.ignore("format", "texel storage precision: ours are half floats")
        p.ignore("accel", "a lookup shortcut of Mitsuba's")
        return {"type": "bitmap", "pixels": pixels.model_dump(), "raw": p.boolean("raw", False),
                "filter": filter_type, "wrap_mode": wrap}

    def _image(self, p: Props, node: Node, plugin: str) -> Pixels:
        """The image file a plugin's `filename` names, found as meshes are (inside the root),
        read within the load budget."""
        filename = p.string("filename")
        if filename is None:
            raise _error(node, f"{plugin} needs a filename")
        named = p.node_of("filename")
        path = self.resolve(named, filename)
        if path.suffix.lower() not in IMAGE_SUFFIXES:
            raise _error(named, f"{filename!r} is not one of {', '.join(IMAGE_SUFFIXES)}")
        return read_texture(path, self.budget, named.file.name, named.where())

    def _diffuse(self, p: Props) -> dict:
        return {"type": "diffuse", "albedo": self._albedo(p, "reflectance", 0.5)}

    def _metal(self, p: Props) -> dict:
        """A conductor's `specular` and, unless Mitsuba's eta is 0, its `eta` and `k`.

        Mitsuba reads eta (default 0) and k (default 1) when `material` is "none" (its
        default) and a named metal's measured data otherwise (refusing eta or k beside a
        name); a name's eta and k here are worker/metals.py's. With eta = 0, eta^2 = -k^2 is
        real and eta^2 - sin^2 negative, so both polarisations' Fresnel ratios are of the form
        |x - i y|^2 / |x + i y|^2 = 1 (x, y real): such a conductor reflects `specular` at every
        angle whatever k, and has no eta and k here.
        """
        if "ext_ior" in p.values:  # Mitsuba 3 refuses it too (an unreferenced property)
            raise _error(p.values["ext_ior"], "a conductor takes no ext_ior: give eta and k relative to "
                                              "the outside")
        out: dict[str, Any] = {"specular": self._albedo(p, "specular_reflectance", 1.0)}
        named = p.node_of("material")
        material = p.string("material", "none")
        if material != "none":
            out["eta"], out["k"] = _named_metal(named, material, p)
            return out
        eta = p.color("eta", 0.0, "unbounded")
        if not any(eta):
            p.ignore("k", "with eta 0 (Mitsuba's default) the Fresnel reflectance is 1 whatever k")
            return out
        out["eta"], out["k"] = list(eta), list(p.color("k", 1.0, "unbounded"))
        return out

    def _microfacet(self, p: Props, textured: bool = False) -> dict:
        """Mitsuba's isotropic microfacet distribution: `alpha` (default 0.1; a texture where
        `textured`, as Mitsuba's roughconductor and roughdielectric take one) and
        `distribution` (beckmann, default, or ggx); `sample_visible` is sampling only."""
        distribution = p.string("distribution", "beckmann")
        if distribution not in ("beckmann", "ggx"):
            raise _error(p.node_of("distribution"), "distribution must be beckmann or ggx")
        texture = self._texture_of(p, "alpha") if textured else None
        if texture is not None:
            p.boolean("sample_visible", True)
            return {"alpha": texture, "distribution": distribution}
        given = [name for name in ("alpha", "alpha_u", "alpha_v") if name in p.values]
        if given not in ([], ["alpha"], ["alpha_u", "alpha_v"]):
            raise _error(p.node_of(given[-1]), "give alpha, or both alpha_u and alpha_v (as Mitsuba requires)")
        alpha = p.number("alpha", 0.1)
        alpha_u, alpha_v = p.number("alpha_u", alpha), p.number("alpha_v", alpha)
        if alpha_u != alpha_v:
            raise _error(p.owner, "anisotropic roughness (alpha_u != alpha_v) is not supported")
        p.boolean("sample_visible", True)
        return {"alpha": alpha_u, "distribution": distribution}

    def _conductor(self, p: Props) -> dict:
        metal = self._metal(p)
        if "eta" not in metal:
            return {"type": "mirror", "albedo": metal["specular"]}
        return {"type": "conductor", **metal}

    def _roughconductor(self, p: Props) -> dict:
        return {"type": "rough_conductor", **self._metal(p), **self._microfacet(p, textured=True)}

    def _ior(self, p: Props, name: str, default: str) -> float:
        node = p.values.get(name)
        if node is not None and node.tag == "string":
            key = p.string(name, default)
            if key not in NAMED_IOR:
                raise _error(node, f"unknown IOR name {key!r}")
            return NAMED_IOR[key]
        value = p.number(name)
        return NAMED_IOR[default] if value is None else value

    def _relative_ior(self, p: Props, interior: str) -> float:
        """Mitsuba's eta = int_ior / ext_ior (numbers or names; the exterior defaults to air),
        which our materials take in [1, 3]."""
        ior = self._ior(p, "int_ior", interior) / self._ior(p, "ext_ior", "air")
        if ior < 1.0:
            raise _error(p.owner, f"int_ior / ext_ior = {ior:g} is below 1 (the outside is denser): ours "
                                  "take interior over exterior, from 1 to 3")
        if ior > 3.0:
            raise _error(p.owner, f"int_ior / ext_ior = {ior:g} must lie in [1, 3]")
        return ior

    def _dielectric(self, p: Props) -> dict:
        out = {"type": "glass", "ior": self._relative_ior(p, "bk7"),
               "albedo": self._albedo(p, "specular_reflectance", 1.0)}
        transmittance = self._albedo(p, "specular_transmittance", 1.0)
        if transmittance != out["albedo"]:  # our glass tints refraction by `albedo` unless told otherwise
            out["transmittance"] = transmittance
        return out

    def _roughdielectric(self, p: Props) -> dict:
        out = {"type": "rough_glass", "ior": self._relative_ior(p, "bk7"),
               "albedo": self._albedo(p, "specular_reflectance", 1.0),
               "transmittance": self._albedo(p, "specular_transmittance", 1.0)}
        return {**out, **self._microfacet(p, textured=True)}

    def _thindielectric(self, p: Props) -> dict:
        return {"type": "thin_glass", "ior": self._relative_ior(p, "bk7"),
                "albedo": self._albedo(p, "specular_reflectance", 1.0),
                "transmittance": self._albedo(p, "specular_transmittance", 1.0)}

    def _plastic(self, p: Props) -> dict:
        return {"type": "plastic", "albedo": self._albedo(p, "diffuse_reflectance", 0.5),
                "specular": self._albedo(p, "specular_reflectance", 1.0),
                "ior": self._relative_ior(p, "polypropylene"), "nonlinear": p.boolean("nonlinear", False)}

    def _roughplastic(self, p: Props) -> dict:
        return {**self._plastic(p), "type": "rough_plastic", **self._microfacet(p)}

    # -------------------------------------------------------------- shapes
    def shape(self, node: Node, parent: np.ndarray | None = None) -> None:
        """Convert a <shape>; `parent` is the to_world of the instance it is flattened through."""
        kind = node.attrs.get("type")
        if kind == "instance":
            self.instance(node, parent)
            return
        if kind == "shapegroup":
            raise _error(node, "a shapegroup belongs at scene level, with an id")
        p = Props(node, self)
        m = p.transform()
        if parent is not None:
            m = parent @ m
        if not abs(np.linalg.det(m[:3, :3])) > 1e-300:
            raise _error(p.node_of("to_world"), "the shape's to_world is singular")
        self._note_id(node)
        builders = {"rectangle": self._rectangle, "cube": self._cube, "sphere": self._sphere, "disk": self._disk,
                    "cylinder": self._cylinder, "obj": self._file_mesh, "ply": self._file_mesh,
                    "serialized": self._file_mesh}
        if kind not in builders:
            raise _error(node, f"unknown shape plugin {kind!r} (have: {', '.join(builders)}, instance, shapegroup)")
        # Its bsdf (nested, referenced, or Mitsuba's default) and its area emitter (nested or referenced).
        material, emission = None, None
        for obj in p.objects:
            target = self.deref(obj) if obj.tag == "ref" else obj
            if target.tag in UNSUPPORTED:
                raise _error(obj, UNSUPPORTED[target.tag])
            if target.tag == "bsdf":
                if material is not None:
                    raise _error(obj, "a shape has one bsdf")
                material = target.attrs["id"] if obj.tag == "ref" else self.bsdf(obj)
            elif target.tag == "emitter":
                if target.attrs.get("type") != "area":
                    raise _error(obj, "a shape's emitter must be an area emitter")
                if emission is not None:
                    raise _error(obj, "a shape has one area emitter")
                ep = Props(target, self)
                emission = list(ep.color("radiance", 1.0, "emission"))
                for inner in ep.objects:
                    raise _error(inner, f"<{inner.tag}> is not supported in an area emitter")
                ep.done()
            else:
                raise _error(obj, f"<{obj.tag}> is not supported in a shape")
        if material is None:  # Mitsuba's default bsdf
            material = "default-diffuse"
            self.materials.setdefault(material, {"type": "diffuse", "albedo": [0.5, 0.5, 0.5]})
        if any(isinstance(v, dict) for v in self.materials[material].values()):
            self._check_uvs(node, kind, m)
        # Its geometry, counted against the triangle limit as the scene grows.
        flip = p.boolean("flip_normals", False)
        shape = builders[kind](p, m, flip)
        p.done()
        self.triangles += 2 if shape["type"] == "quad" else len(shape.get("triangles", ()))
        if self.triangles > MAX_TRIANGLES:
            raise _error(node, f"the scene has more than {MAX_TRIANGLES} triangles")
        shape["material"] = material
        if emission is not None:
            shape["emission"] = emission
        self.origin[f"shapes.{len(self.shapes)}"] = node
        self.shapes.append(shape)

    def instance(self, node: Node, parent: np.ndarray | None) -> None:
        """An instance, flattened: each shape of its shapegroup through the instance's to_world."""
        p = Props(node, self)
        m = p.transform() if parent is None else parent @ p.transform()
        refs = [o for o in p.objects if o.tag == "ref"]
        if len(refs) != 1 or len(p.objects) != 1:
            raise _error(node, "an instance takes exactly one <ref> to a shapegroup")
        group = self.deref(refs[0])
        if group.tag != "shape" or group.attrs.get("type") != "shapegroup":
            raise _error(refs[0], f"{refs[0].attrs.get('id')!r} is not a shapegroup")
        p.done()
        for child in group.children:
            if child.tag != "shape" or child.attrs.get("type") in ("instance", "shapegroup"):
                raise _error(child, "a shapegroup holds shapes (no instances or groups)")
            self.shape(child, m)

    @staticmethod
    def _check_uvs(node: Node, kind: str | None, m: np.ndarray) -> None:
        """A textured shape's texture coordinates must be Mitsuba's: every shape's are, but for
        a rotated sphere's (ours are taken about the world's axes)."""
        if kind == "sphere":
            r = m[:3, :3] / np.linalg.norm(m[:3, 0])
            if not np.allclose(r, np.eye(3), atol=1e-9):
                raise _error(node, "a textured sphere's to_world may not rotate (its texture coordinates "
                                   "are taken about the world's axes)")

    @staticmethod
    def _mesh(vertices: np.ndarray, triangles: np.ndarray, normals: np.ndarray | None, flip: bool,
              uvs: np.ndarray | None = None) -> dict:
        if flip:
            triangles = triangles[:, ::-1]
        out = {"type": "mesh", "vertices": vertices, "triangles": triangles}
        if normals is not None:
            out["normals"] = -normals if flip else normals
        if uvs is not None:
            out["uvs"] = uvs
        return out

    def _rectangle(self, p: Props, m: np.ndarray, flip: bool) -> dict:
        """Mitsuba's rectangle [-1, 1]^2 with texture coordinates ((x + 1) / 2, (y + 1) / 2)."""
        corner, c1, c2 = _apply(m, np.array([[-1.0, -1, 0], [1, -1, 0], [-1, 1, 0]]))
        e1, e2 = c1 - corner, c2 - corner
        normal = np.linalg.inv(m[:3, :3]).T @ np.array([0, 0, -1.0 if flip else 1.0])  # Mitsuba's front side
        out = {"type": "quad", "corner": corner.tolist(), "edge1": e1.tolist(), "edge2": e2.tolist()}
        if np.dot(np.cross(e1, e2), normal) < 0:
            out.update(edge1=e2.tolist(), edge2=e1.tolist(), uvs=[[0.0, 0.0], [0.0, 1.0], [1.0, 1.0], [1.0, 0.0]])
        return out

    def _cube(self, p: Props, m: np.ndarray, flip: bool) -> dict:
        """[-1, 1]^3 as Mitsuba's cube: four corners a face (CUBE_FACES), wound counter-clockwise
        seen from outside, with its texture coordinates (0, 1), (1, 1), (1, 0), (0, 0)."""
        corners = np.array(CUBE_FACES, np.float64).reshape(-1, 3)
        first = 4 * np.arange(6)[:, None]
        tris = np.concatenate([first + [0, 1, 2], first + [3, 0, 2]], axis=1).reshape(-1, 3)
        uvs = np.tile([[0.0, 1.0], [1.0, 1.0], [1.0, 0.0], [0.0, 0.0]], (6, 1))
        if np.linalg.det(m[:3, :3]) < 0:
            tris = tris[:, ::-1]
        return self._mesh(_apply(m, corners), tris, None, flip, uvs)

    def _disk(self, p: Props, m: np.ndarray, flip: bool) -> dict:
        """The unit disk as a fan of DISK_SEGMENTS triangles, with Mitsuba's texture
        coordinates (r, phi / 2 pi): each triangle has a centre of its own, at the middle of
        its angles, and the ring repeats its first point at phi = 2 pi."""
        k = np.arange(DISK_SEGMENTS)
        phi = 2 * math.pi * np.arange(DISK_SEGMENTS + 1) / DISK_SEGMENTS
        ring = np.stack([np.cos(phi), np.sin(phi), np.zeros_like(phi)], axis=1)
        points = np.concatenate([np.zeros((DISK_SEGMENTS, 3)), ring])
        uvs = np.concatenate([np.c_[np.zeros(DISK_SEGMENTS), (k + 0.5) / DISK_SEGMENTS],
                              np.c_[np.ones(DISK_SEGMENTS + 1), phi / (2 * math.pi)]])
        tris = np.stack([k, DISK_SEGMENTS + k, DISK_SEGMENTS + k + 1], axis=1)
        if np.linalg.det(m[:3, :3]) < 0:
            tris = tris[:, ::-1]
        return self._mesh(_apply(m, points), tris, None, flip, uvs)

    def _sphere(self, p: Props, m: np.ndarray, flip: bool) -> dict:
        center = p.vector("center", "point")
        radius = p.number("radius", 1.0)
        r = m[:3, :3]
        # The scale: each column's length, if uniform (exact for an exact scale; the cube
        # root of the determinant is not: 3.0000000000000004 for 27 with NumPy's scalar cbrt
        # on some CPUs).
        s = float(np.linalg.norm(r, axis=0).mean())
        if not np.allclose(r.T @ r, s * s * np.eye(3), rtol=1e-6, atol=1e-9 * max(s * s, 1e-300)):
            raise _error(p.owner, "a sphere's to_world may only scale uniformly, rotate and translate")
        c = _apply(m, (center if center is not None else np.zeros(3))[None])[0]
        if flip:
            raise _error(p.node_of("flip_normals"), "flip_normals is not supported on spheres")
        return {"type": "sphere", "center": c.tolist(), "radius": radius * s}

    def _file_mesh(self, p: Props, m: np.ndarray, flip: bool) -> dict:
        filename = p.string("filename")
        if filename is None:
            raise _error(p.owner, "a mesh needs a filename")
        path = self.resolve(p.node_of("filename"), filename)
        face_normals = p.boolean("face_normals", False)
        kind = p.owner.attrs["type"]
        # Ours read an OBJ's texture coordinates with v turned to 1 - v, as Mitsuba's default.
        flip_v = kind == "obj" and not p.boolean("flip_tex_coords", True)
        named = p.node_of("filename")
        try:
            if kind == "serialized":
                index = p.integer("shape_index", 0)
                mesh, flat = self._serialized(path, index, named)
                face_normals = face_normals or flat
            else:
                mesh = read_mesh(path, self.budget, named.file.name, named.where())
        except OSError as exc:
            raise _error(named, f"cannot read {filename}: {exc.strerror or exc}") from None
        except MeshError as exc:
            raise _error(named, f"{filename}: {exc}") from None
        tris = mesh.triangles
        world = _apply(m, mesh.vertices)
        normals = None
        if mesh.normals is not None and not face_normals:  # normals transform by the inverse transpose
            normals = _times(mesh.normals, np.linalg.inv(m[:3, :3]))
        elif not face_normals:  # Mitsuba computes angle-weighted vertex normals from the placed mesh
            normals = _vertex_normals(world, tris)
        if np.linalg.det(m[:3, :3]) < 0:
            tris = tris[:, ::-1]
        uvs = mesh.uvs
        if uvs is not None and flip_v:
            uvs = np.column_stack([uvs[:, 0], 1.0 - uvs[:, 1]])
        return self._mesh(world, tris, normals, flip, uvs)

    def _serialized(self, path: Path, index: int, named: Node) -> tuple[MeshData, bool]:
        """Shape `index` of a serialized file and whether it asks for face normals, read
        within the budget (its header's counts checked before the mesh is decompressed)."""
        field, at = named.file.name, named.where()
        data = self.budget.read(path, "mesh files", field, at)
        vertices, triangles = header_counts(data, index)
        self.budget.check("mesh vertices", vertices, field, at)
        self.budget.check("triangles", triangles, field, at)
        shape = read_serialized(data, index)
        self.budget.take("mesh vertices", vertices, field, at)
        self.budget.take("triangles", triangles, field, at)
        return shape.mesh, shape.face_normals

    def _cylinder(self, p: Props, m: np.ndarray, flip: bool) -> dict:
        """Mitsuba's cylinder as a mesh: the open tube of `radius` from p0 to p1 (default a unit
        radius from the origin to +z), CYLINDER_SEGMENTS quads with radial smooth normals."""
        p0 = p.vector("p0", "point")
        p1 = p.vector("p1", "point")
        p0 = np.zeros(3) if p0 is None else p0
        p1 = np.array([0.0, 0.0, 1.0]) if p1 is None else p1
        radius = p.number("radius", 1.0) or 0.0
        axis = p1 - p0
        if not (np.linalg.norm(axis) > 0 and radius > 0):
            raise _error(p.owner, "a cylinder needs p0 != p1 and a positive radius")
        # Mitsuba's frame about the axis (the basis of _some_up): phi counts from its first tangent.
        w = axis / np.linalg.norm(axis)
        u = _some_up(w)
        local = np.eye(4)
        local[:3, 0], local[:3, 1], local[:3, 2], local[:3, 3] = radius * u, radius * np.cross(w, u), axis, p0
        full = m @ local
        # A ring of CYLINDER_SEGMENTS + 1 points (the first repeated at phi = 2 pi) at z = 0 and
        # z = 1, with Mitsuba's texture coordinates (phi / 2 pi, z).
        phi = 2 * math.pi * np.arange(CYLINDER_SEGMENTS + 1) / CYLINDER_SEGMENTS
        ring = np.stack([np.cos(phi), np.sin(phi)], axis=1)
        points = np.concatenate([np.c_[ring, np.zeros(len(ring))], np.c_[ring, np.ones(len(ring))]])
        uvs = np.concatenate([np.c_[phi / (2 * math.pi), np.zeros(len(ring))],
                              np.c_[phi / (2 * math.pi), np.ones(len(ring))]])
        radial = np.c_[ring, np.zeros(len(ring))]
        k, n = np.arange(CYLINDER_SEGMENTS), CYLINDER_SEGMENTS + 1
        nxt = k + 1
        tris = np.concatenate([np.stack([k, nxt, n + nxt], 1), np.stack([k, n + nxt, n + k], 1)])
        if np.linalg.det(full[:3, :3]) < 0:
            tris = tris[:, ::-1]
        normals = np.concatenate([radial, radial]) @ np.linalg.inv(full[:3, :3])
        return self._mesh(_apply(full, points), tris, normals, flip, uvs)

    # -------------------------------------------------------------- lights
    def light(self, node: Node) -> None:
        kind = node.attrs.get("type")
        self._note_id(node)
        p = Props(node, self)
        for obj in p.objects:
            raise _error(obj, f"<{obj.tag}> is not supported in an emitter")
        if kind == "point":
            m = p.transform()
            pos = p.vector("position", "point")
            position = _apply(m, (pos if pos is not None else np.zeros(3))[None])[0]
            power = 4 * math.pi * np.array(p.color("intensity", 1.0, "emission"))
            light = {"type": "point", "position": position.tolist(), "power": power.tolist()}
        elif kind == "spot":
            m = p.transform()
            cutoff = p.number("cutoff_angle", 20.0)
            beam = p.number("beam_width", 0.75 * cutoff)
            if beam < cutoff * (1 - 1e-3):
                raise _error(p.node_of("beam_width"), "our spot light is uniform inside its cone: beam_width "
                                                       "must equal cutoff_angle (no falloff)")
            if not 0 < cutoff <= 90:
                raise _error(p.node_of("cutoff_angle"), "cutoff_angle must lie in (0, 90]")
            solid_angle = 2 * math.pi * (1 - math.cos(math.radians(cutoff)))
            power = solid_angle * np.array(p.color("intensity", 1.0, "emission"))
            light = {"type": "spot", "position": m[:3, 3].tolist(), "direction": m[:3, 2].tolist(),
                     "cone_angle": cutoff, "power": power.tolist()}
        elif kind == "directional":
            m = p.transform()
            d = p.vector("direction", "vector")
            direction = m[:3, :3] @ (d if d is not None else np.array([0.0, 0.0, 1.0]))
            light = {"type": "directional", "direction": direction.tolist(),
                     "irradiance": list(p.color("irradiance", 1.0, "emission"))}
        elif kind == "constant":
            light = {"type": "environment", "radiance": list(p.color("radiance", 1.0, "emission"))}
        elif kind == "envmap":
            light = self._envmap(p)
        elif kind == "area":
            raise _error(node, "an area emitter belongs inside a shape")
        else:
            raise _error(node, f"unknown emitter plugin {kind!r} (have: point, spot, directional, constant, envmap, "
                               "area in a shape)")
        p.done()
        self.origin[f"lights.{len(self.lights)}"] = node
        self.lights.append(light)

    def _envmap(self, p: Props) -> dict:
        """An envmap: its image read now (found as meshes are, inside the root) and carried
        inline among the scene's textures; its to_world a rotation (Mitsuba maps directions
        by the inverse without normalising: a scale would bend its sky)."""
        pixels = self._image(p, p.owner, "an envmap")
        where = p.node_of("to_world")
        r = p.transform()[:3, :3]
        if not np.allclose(r @ r.T, np.eye(3), atol=ROTATION_TOLERANCE):
            raise _error(where, "an envmap's to_world must be a rotation (no scale or shear)")
        p.ignore("mis_compensation", "it changes how the map is sampled, not the image")
        name = p.owner.attrs.get("id", "envmap")
        while name in self.textures:  # an unnamed envmap beside a texture of that name
            name += "_"
        self.textures[name] = {"type": "bitmap", "pixels": pixels.model_dump()}
        return {"type": "environment", "map": name, "scale": p.number("scale", 1.0), "to_world": r.tolist()}

    # -------------------------------------------------------------- result
    def result(self, top: Node) -> dict:
        if self.camera is None:
            raise _error(top, "the scene has no sensor")
        for name, node in self.named.items():  # as Mitsuba: defined, never used, not rendered
            if node.tag in ("emitter", "texture", "shape") and name not in self.referenced:
                self.note(node, node, f"id {name!r}", "defined but never referenced")
        return {"description": f"converted from {top.file.name} (Mitsuba 3)", "camera": self.camera,
                "materials": self.materials, "shapes": self.shapes, "lights": self.lights,
                **({"textures": self.textures} if self.textures else {})}


def _vertex_normals(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Angle-weighted vertex normals (Thuermer and Wuethrich 1998, as Mitsuba computes them):
    each face adds its unit normal times its angle at the vertex. Zero for a vertex that only
    degenerate faces touch (the renderer then takes the face normal)."""
    weighted = np.empty((3, len(triangles), 3))  # [axis, triangle, corner]: what the corner adds
    for start in range(0, len(triangles), NORMALS_CHUNK):
        part = slice(start, start + NORMALS_CHUNK)
        p = vertices[triangles[part]]  # (n, 3, 3): corner k of each triangle
        edge = np.roll(p, -1, axis=1) - p  # edge k leaves corner k
        unit = edge / np.maximum(_lengths(edge), 1e-300)[..., None]
        face = np.cross(edge[:, 0], -edge[:, 2])
        face /= np.maximum(_lengths(face), 1e-300)[:, None]
        # The angle at a corner is between its outgoing edge and the reversed incoming one.
        cos = -np.einsum("tkj,tkj->tk", unit, np.roll(unit, 1, axis=1))
        np.multiply(face.T[:, :, None], np.arccos(np.clip(cos, -1.0, 1.0)), out=weighted[:, part])
    corners = triangles.ravel()
    out = np.stack([np.bincount(corners, weighted[axis].ravel(), minlength=len(vertices)) for axis in range(3)],
                   axis=1)
    return out / np.maximum(_lengths(out), 1e-300)[:, None]


def _lengths(v: np.ndarray) -> np.ndarray:
    """Euclidean lengths along the last axis."""
    return np.sqrt(np.einsum("...j,...j->...", v, v))


def convert_mitsuba(path: Path | str, params: dict[str, str] | None = None, root: Path | None = None,
                    budget: LoadBudget | None = None, notes: list[str] | None = None) -> dict:
    """Our scene JSON from a Mitsuba 3 XML file; `params` override its <default>s. Meshes
    are inlined (transformed). Files it names are found as Mitsuba's resolver finds them and
    must lie inside `root` (default: its folder); they are read within `budget` (a new one if
    none). The result is validated: errors name the XML element and line that produced the
    value. What was accepted but ignored is appended to `notes`, one line each."""
    data, _, found = convert_and_validate(path, params, root, budget)
    if notes is not None:
        notes.extend(found)
    with collector_paused():
        for shape in data["shapes"]:  # a mesh's arrays as JSON's lists
            shape.update({key: value.tolist() for key, value in shape.items() if isinstance(value, np.ndarray)})
    return data


def convert_and_validate(path: Path | str, params: dict[str, str] | None = None, root: Path | None = None,
                         budget: LoadBudget | None = None) -> tuple[dict, Scene, list[str]]:
    """`convert_mitsuba`'s JSON (a mesh's vertices, triangles and normals still NumPy arrays),
    the Scene it validated to (validated once) and the notes."""
    path = Path(path).resolve()
    conv = Converter(root=(root or path.parent).resolve(), params={k: str(v) for k, v in (params or {}).items()},
                     budget=budget or LoadBudget())
    top = _read_xml(path, conv.budget)
    conv.start(top)
    conv.scene(top)
    data = conv.result(top)
    try:
        scene = parse_scene(data)
    except SceneError as exc:
        parts = exc.field.split(".")
        for n in (2, 1):
            node = conv.origin.get(".".join(parts[:n]))
            if node is not None:
                raise SceneError(node.file.name, f"{node.where()}: {exc.field}: {exc.message}") from None
        raise
    return data, scene, conv.notes
