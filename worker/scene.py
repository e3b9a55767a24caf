"""Scene description: the JSON schema (pydantic), its limits, and loading.

The model holds no more than the bundled scenes need: a pinhole or thin-lens camera,
spheres, quads and triangle meshes (any of which may emit and is then an area light),
ten materials and three kinds of delta light. Every validation failure is reported
as a `SceneError` whose `field` is the dotted path of the offending value, so the CLI
and the HTTP API can name it.
"""

from __future__ import annotations

import gc
import json
import math
import re
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from itertools import chain
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import (
    BaseModel,
    ConfigDict,
    Discriminator,
    Field,
    GetCoreSchemaHandler,
    StrictInt,
    Tag,
    ValidationError,
    ValidatorFunctionWrapHandler,
    field_validator,
    model_validator,
)
from pydantic_core import CoreSchema, core_schema

from worker.images import IMAGE_SUFFIXES, ImageError, Pixels, image_shape, read_image
from worker.meshes import MESH_SUFFIXES, MeshData, MeshError, check_mesh, declared_counts, load_mesh

SCENES_DIR = Path(__file__).resolve().parent.parent / "scenes"

# Documented limits (docs/limits.md). They bound memory and kernel time per pass.
MAX_RESOLUTION = 8192  # pixels along either image axis
MAX_PIXELS = 8192 * 4320
MAX_SHAPES = 10_000
MAX_TRIANGLES = 500_000  # after quads are split and meshes loaded
MAX_LIGHTS = 64
MAX_COORD = 1e7  # |coordinate| bound: keeps float32 positions meaningful
MAX_PATH_CHARS = 255  # a mesh file name: what a file system accepts for one name
SCENE_NAME_PATTERN = r"^[a-z0-9][a-z0-9-]*$"  # a bundled scene's name: never a path
MAX_SCENE_NAME = 64
# What one scene load may do in all, whatever the scene's shape (README, "Limits"): a file
# counts every time it is opened, so K includes of K includes cost K^2 files, not K. Real
# scenes (Mitsuba's published ones: hundreds of includes and meshes at most) pass far below.
MAX_XML_DEPTH = 64  # elements nested in one XML file
MAX_INCLUDE_DEPTH = 8  # XML includes nested
LOAD_LIMITS = {
    "scene files": 1_000,  # the scene file and every XML inclusion
    "XML elements": 200_000,  # in all XML files read, each time it is read
    "mesh files": 2_000,  # each mesh file, each time a shape names it
    "bytes": 64 * 1024 * 1024,  # read from every file together
    "mesh vertices": 3 * MAX_TRIANGLES,  # as declared in mesh files (checked before they are parsed)
    "triangles": MAX_TRIANGLES,  # read from mesh files (declared counts checked before parsing)
    "image files": 1_000,  # textures and environment maps
    "texels": 2**26,  # samples of every image read (declared sizes checked before decoding)
}

# Numbers are strict: a string or a boolean where one belongs is refused, not coerced (JSON lists
# still make the tuples).
Coord = Annotated[float, Field(strict=True, allow_inf_nan=False, ge=-MAX_COORD, le=MAX_COORD)]
Vec3 = tuple[Coord, Coord, Coord]
Unit = Annotated[float, Field(strict=True, allow_inf_nan=False, ge=0.0, le=1.0)]
Albedo = tuple[Unit, Unit, Unit]
NonNeg = Annotated[float, Field(strict=True, allow_inf_nan=False, ge=0.0, le=1e12)]
Power = tuple[NonNeg, NonNeg, NonNeg]
Side = Annotated[int, Field(strict=True, ge=1, le=MAX_RESOLUTION)]  # pixels along one image axis


def _rows_out(rows: np.ndarray, info: core_schema.SerializationInfo) -> np.ndarray | list:
    """A mesh's rows as written: lists in JSON, the array itself in a Python dump."""
    return rows.tolist() if info.mode_is_json() else rows


@dataclass(frozen=True)
class _Rows:
    """A pydantic annotation: a mesh's rows of `width` values (vertices, normals, triangles: 3;
    texture coordinates: 2) held as an (n, width) NumPy array of `dtype`. A value is accepted
    exactly when pydantic accepts it as `rows` (the list-of-rows type the array stands for),
    with the same errors: a list of rows of `scalars` (what JSON gives) or an array of
    `kinds` is checked vectorised, and anything else, or anything that fails that check, goes
    to pydantic's validator of `rows`, which names the bad element. JSON output is the list
    of rows."""

    rows: Any
    dtype: type[np.generic]
    scalars: frozenset[type]  # Python types `rows` accepts as elements with no conversion
    kinds: str  # NumPy dtype kinds an array may come in
    valid: Callable[[np.ndarray], bool]  # every element meets the element type's constraints
    width: int = 3  # values a row

    def __get_pydantic_core_schema__(self, source: Any, handler: GetCoreSchemaHandler) -> CoreSchema:
        return core_schema.no_info_wrap_validator_function(
            self._validate, handler.generate_schema(self.rows),
            serialization=core_schema.plain_serializer_function_ser_schema(_rows_out, info_arg=True))

    def _validate(self, value: Any, handler: ValidatorFunctionWrapHandler) -> np.ndarray:
        fast = self._fast(value)
        if fast is not None:
            return fast
        rows = handler(value.tolist() if isinstance(value, np.ndarray) else value)
        try:
            return np.array(rows, self.dtype).reshape(-1, self.width)
        except OverflowError:  # an index past int64, which no vertex has: -1 is as far out of range
            return np.array([[i if abs(i) < 2**63 else -1 for i in row] for row in rows], self.dtype)

    def _fast(self, value: Any) -> np.ndarray | None:
        """`value` as an array if it is surely valid; None to leave it to pydantic."""
        if isinstance(value, list):
            if not (set(map(type, value)) <= {list, tuple} and set(map(len, value)) <= {self.width}
                    and set(map(type, chain.from_iterable(value))) <= self.scalars):
                return None
            try:
                value = np.array(value, self.dtype)
            except OverflowError:
                return None
        elif not (isinstance(value, np.ndarray) and value.ndim == 2 and value.shape[1] == self.width
                  and value.dtype.kind in self.kinds and np.can_cast(value.dtype, self.dtype)):
            return None
        rows = np.ascontiguousarray(value, self.dtype).reshape(-1, self.width)
        return rows if self.valid(rows) else None


# Mesh rows: vertices and normals as list[Vec3] would be, triangles as triples of StrictInt.
Vec3Rows = Annotated[np.ndarray, _Rows(list[Vec3], np.float64, frozenset({float, int}), "fiu",
                                       lambda a: bool(np.all(np.abs(a) <= MAX_COORD)))]
IndexRows = Annotated[np.ndarray, _Rows(list[tuple[StrictInt, StrictInt, StrictInt]], np.int64, frozenset({int}),
                                        "iu", lambda a: True)]
UvRows = Annotated[np.ndarray, _Rows(list[tuple[Coord, Coord]], np.float64, frozenset({float, int}), "fiu",
                                     lambda a: bool(np.all(np.abs(a) <= MAX_COORD)), width=2)]


class SceneError(ValueError):
    """A scene that cannot be rendered; `field` is the dotted path of the bad value."""

    def __init__(self, field: str, message: str) -> None:
        super().__init__(f"{field}: {message}" if field else message)
        self.field = field
        self.message = message


class SceneLimitError(SceneError):
    """A scene load that ran past one of LOAD_LIMITS (the API answers 413)."""


class LoadBudget:
    """The work one scene load has done, against LOAD_LIMITS: one object is passed through
    the whole load (JSON or XML, every include, every mesh). Running out raises a
    SceneLimitError with `field` (the file, or the scene field) and `at` (e.g. its line)."""

    def __init__(self) -> None:
        self.used = dict.fromkeys(LOAD_LIMITS, 0)

    def check(self, what: str, amount: int, field: str, at: str = "") -> None:
        """Refuse `amount` more of `what` if it would pass the limit; counts nothing."""
        limit = LOAD_LIMITS[what]
        if self.used[what] + amount > limit:
            raise SceneLimitError(field, f"{at + ': ' if at else ''}the scene needs more than {limit} {what} "
                                         "(the limit for one scene load)")

    def take(self, what: str, amount: int, field: str, at: str = "") -> None:
        self.check(what, amount, field, at)
        self.used[what] += amount

    def read(self, path: Path, kind: str, field: str, at: str = "") -> bytes:
        """A file's bytes, counted as one of `kind` ("scene files", "mesh files") and in bytes;
        a file past the remaining bytes is refused without reading it all."""
        self.take(kind, 1, field, at)
        with path.open("rb") as fh:
            data = fh.read(LOAD_LIMITS["bytes"] - self.used["bytes"] + 1)
        self.take("bytes", len(data), field, at)
        return data


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


def _norm(v: Sequence[float]) -> float:
    return math.sqrt(v[0] ** 2 + v[1] ** 2 + v[2] ** 2)


# ----------------------------------------------------------------------------- camera
class Camera(_Model):
    position: Vec3
    look_at: Vec3
    up: Vec3 = (0.0, 1.0, 0.0)
    fov: Annotated[float, Field(strict=True, gt=0.0, lt=180.0, allow_inf_nan=False)] = 40.0  # vertical, degrees
    resolution: tuple[Side, Side] = (512, 512)
    aperture_radius: NonNeg = 0.0  # thin lens when > 0
    # Defaults to |look_at - position|.
    focus_distance: Annotated[float, Field(strict=True, gt=0.0, allow_inf_nan=False)] | None = None
    near_clip: NonNeg = 0.0  # rays start this far along the view axis (smallppm starts them past its front wall)

    @model_validator(mode="after")
    def _check(self) -> Camera:
        forward = tuple(a - b for a, b in zip(self.look_at, self.position, strict=True))
        if _norm(forward) == 0.0:
            raise ValueError("look_at equals position")
        cross = np.cross(np.array(forward), np.array(self.up))
        if float(np.linalg.norm(cross)) <= 1e-9 * _norm(forward) * max(_norm(self.up), 1e-30):
            raise ValueError("up is parallel to the view direction")
        if self.resolution[0] * self.resolution[1] > MAX_PIXELS:
            raise ValueError(f"resolution has more than {MAX_PIXELS} pixels")
        return self


# -------------------------------------------------------------------------- materials
class TextureRef(_Model):
    """One of the scene's `textures`, by name, where a colour or a roughness is accepted: the
    value is the texture's at the hit's UV."""

    texture: Annotated[str, Field(min_length=1, max_length=MAX_PATH_CHARS)]


# Tags of the constant-or-texture unions: a value is a texture reference when it is an object.
CONSTANT, REFERENCE = "constant", "texture_ref"


def _constant_or_reference(value: object) -> str:
    return REFERENCE if isinstance(value, dict | TextureRef) else CONSTANT


Colour = Annotated[Annotated[Albedo, Tag(CONSTANT)] | Annotated[TextureRef, Tag(REFERENCE)],
                   Discriminator(_constant_or_reference)]
# An opacity that may vary over the surface: a texture's values (a bitmap's luminance, a
# checkerboard's channel mean, as Mitsuba 3's eval_1) are clamped to [0, 1].
Opacity = Annotated[Annotated[Unit, Tag(CONSTANT)] | Annotated[TextureRef, Tag(REFERENCE)],
                    Discriminator(_constant_or_reference)]


class _Material(_Model):
    """What every material has: its `opacity`, the share of the surface that is there
    (Mitsuba 3's mask); the rest passes light straight through, as a cut-out leaf or a fence."""

    opacity: Opacity = 1.0


class Diffuse(_Material):
    type: Literal["diffuse"]
    albedo: Colour


class Mirror(_Material):
    type: Literal["mirror"]
    albedo: Colour = (1.0, 1.0, 1.0)


Ior = Annotated[float, Field(strict=True, ge=1.0, le=3.0, allow_inf_nan=False)]  # interior / exterior
# Microfacet roughness (the distribution's alpha): below 0.001 a lobe is a mirror in all but
# the float32 arithmetic of its pdf.
Roughness = Annotated[float, Field(strict=True, ge=0.001, le=1.0, allow_inf_nan=False)]
# A roughness that may vary over the surface (where Mitsuba allows a texture): a texture's
# values are clamped to Roughness's range.
VaryingRoughness = Annotated[Annotated[Roughness, Tag(CONSTANT)] | Annotated[TextureRef, Tag(REFERENCE)],
                             Discriminator(_constant_or_reference)]
Distribution = Literal["beckmann", "ggx"]
EtaPart = Annotated[float, Field(strict=True, gt=0.0, le=100.0, allow_inf_nan=False)]
KPart = Annotated[float, Field(strict=True, ge=0.0, le=100.0, allow_inf_nan=False)]


class Glass(_Material):
    """Smooth dielectric: Fresnel reflection tinted by `albedo`, refraction by `transmittance`."""

    type: Literal["glass"]
    ior: Ior = 1.5
    albedo: Colour = (1.0, 1.0, 1.0)  # tint of reflection (and of refraction unless `transmittance`)
    transmittance: Colour | None = None


class RoughGlass(Glass):
    """A dielectric with a rough surface: microfacet reflection and refraction of roughness
    `alpha`."""

    type: Literal["rough_glass"]  # type: ignore[assignment]
    alpha: VaryingRoughness = 0.1
    distribution: Distribution = "beckmann"


class ThinGlass(_Material):
    """A thin dielectric sheet (a window pane): the interreflections inside it summed, rays pass
    straight through."""

    type: Literal["thin_glass"]
    ior: Ior = 1.5
    albedo: Colour = (1.0, 1.0, 1.0)
    transmittance: Colour = (1.0, 1.0, 1.0)


class Glossy(_Material):
    """Modified Phong lobe f = albedo (n+2)/(2 pi) cos^n(angle to the mirror direction)."""

    type: Literal["glossy"]
    albedo: Colour
    exponent: Annotated[float, Field(strict=True, ge=1.0, le=100_000.0, allow_inf_nan=False)]


class _Metal(_Material):
    """A conductor's complex index of refraction eta + i k per rgb channel (relative to the
    exterior); without them the surface reflects `specular` at every angle (no Fresnel term)."""

    specular: Colour = (1.0, 1.0, 1.0)
    eta: tuple[EtaPart, EtaPart, EtaPart] | None = None
    k: tuple[KPart, KPart, KPart] | None = None

    @model_validator(mode="after")
    def _check_pair(self) -> _Metal:
        if (self.eta is None) != (self.k is None):
            raise ValueError("give both eta and k, or neither")
        return self


class Conductor(_Metal):
    type: Literal["conductor"]


class RoughConductor(_Metal):
    type: Literal["rough_conductor"]
    alpha: VaryingRoughness = 0.1
    distribution: Distribution = "beckmann"


class Plastic(_Material):
    """A diffuse base (`albedo`) under a smooth dielectric coat of index `ior`; `nonlinear`
    accounts for the colour shift of light scattered inside the coat."""

    type: Literal["plastic"]
    albedo: Colour = (0.5, 0.5, 0.5)
    specular: Colour = (1.0, 1.0, 1.0)
    ior: Ior = 1.49
    nonlinear: bool = False


class RoughPlastic(Plastic):
    """Plastic with a rough coat: a microfacet lobe of roughness `alpha` over the diffuse base."""

    type: Literal["rough_plastic"]  # type: ignore[assignment]
    alpha: Roughness = 0.1
    distribution: Distribution = "beckmann"


Material = Annotated[
    Diffuse | Mirror | Glass | RoughGlass | ThinGlass | Glossy | Conductor | RoughConductor | Plastic | RoughPlastic,
    Field(discriminator="type"),
]

# ---------------------------------------------------------------------------- textures
# A 2x3 affine map of (u, v, 1): where a hit's surface UV is looked up in a texture.
UvTransform = tuple[Vec3, Vec3]
IDENTITY_UV: UvTransform = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0))
FileName = Annotated[str, Field(min_length=1, max_length=MAX_PATH_CHARS, pattern=r"^[^\x00]*$")]


class Bitmap(_Model):
    """An image: a `file` (relative to the scene file, inside the root the caller allows) or
    its `pixels` inline. Integer images are sRGB-encoded unless `raw`; float images are linear."""

    type: Literal["bitmap"]
    file: FileName | None = None
    pixels: Pixels | None = None
    raw: bool = False
    filter: Literal["bilinear", "nearest"] = "bilinear"
    wrap_mode: Literal["repeat", "mirror", "clamp"] = "repeat"
    to_uv: UvTransform = IDENTITY_UV

    @model_validator(mode="after")
    def _check(self) -> Bitmap:
        if (self.file is None) == (self.pixels is None):
            raise ValueError("give either file or pixels")
        return self


class Checkerboard(_Model):
    """color0 where floor(u) + floor(v) is even (after `to_uv`, in units of a cell), color1 elsewhere."""

    type: Literal["checkerboard"]
    color0: Albedo = (0.4, 0.4, 0.4)
    color1: Albedo = (0.2, 0.2, 0.2)
    to_uv: UvTransform = IDENTITY_UV


Texture = Annotated[Bitmap | Checkerboard, Field(discriminator="type")]
MAX_TEXTURES = 256

# ----------------------------------------------------------------------------- shapes


class _Shape(_Model):
    material: str
    emission: Power | None = None  # radiance leaving the front side: the shape is an area light


class Sphere(_Shape):
    type: Literal["sphere"]
    center: Vec3
    radius: Annotated[float, Field(strict=True, gt=0.0, le=MAX_COORD, allow_inf_nan=False)]


Uv = tuple[Coord, Coord]
QUAD_UVS: tuple[Uv, Uv, Uv, Uv] = ((0.0, 0.0), (1.0, 0.0), (1.0, 1.0), (0.0, 1.0))


class Quad(_Shape):
    """Parallelogram corner + s*edge1 + t*edge2, s,t in [0,1]; front side along edge1 x edge2.
    `uvs`: the texture coordinates of corner, corner + edge1, corner + edge1 + edge2 and
    corner + edge2 (default (s, t)), bilinear between them."""

    type: Literal["quad"]
    corner: Vec3
    edge1: Vec3
    edge2: Vec3
    uvs: tuple[Uv, Uv, Uv, Uv] | None = None  # None: QUAD_UVS


class Mesh(_Shape):
    """Triangles given inline (optionally with per-vertex shading `normals`) or as an .obj
    or .ply `file`, relative to the scene file and inside the root the caller allows."""

    type: Literal["mesh"]
    vertices: Vec3Rows | None = None  # (V, 3) float64
    triangles: IndexRows | None = None  # (T, 3) int64
    normals: Vec3Rows | None = None  # (V, 3) float64
    uvs: UvRows | None = None  # (V, 2) float64 texture coordinates; without them a triangle's are (b1, b2)
    file: FileName | None = None

    @model_validator(mode="after")
    def _check(self) -> Mesh:
        if (self.file is None) == (self.vertices is None or self.triangles is None):
            raise ValueError("give either file or both vertices and triangles")
        if self.normals is not None and (self.vertices is None or len(self.normals) != len(self.vertices)):
            raise ValueError("normals need inline vertices, one normal per vertex")
        if self.uvs is not None and (self.vertices is None or len(self.uvs) != len(self.vertices)):
            raise ValueError("uvs need inline vertices, one uv per vertex")
        if self.triangles is not None and len(self.triangles) > MAX_TRIANGLES:
            raise ValueError(f"more than {MAX_TRIANGLES} triangles")
        if self.vertices is not None and self.triangles is not None and len(self.triangles):
            n = len(self.vertices)
            bad = np.flatnonzero((self.triangles.min(axis=1) < 0) | (self.triangles.max(axis=1) >= n))
            if len(bad):
                raise ValueError(f"triangles[{bad[0]}] indexes a vertex outside 0..{n - 1}")
        return self

    def __eq__(self, other: object) -> bool:
        """Field by field, arrays by value (pydantic's comparison asks arrays for one truth value)."""
        if not isinstance(other, Mesh):
            return NotImplemented
        return all(np.array_equal(getattr(self, name), getattr(other, name)) for name in Mesh.model_fields)


Shape = Annotated[Sphere | Quad | Mesh, Field(discriminator="type")]

# ----------------------------------------------------------------------------- lights


def _nonzero_direction(v: tuple[float, float, float]) -> tuple[float, float, float]:
    if _norm(v) == 0.0:
        raise ValueError("direction must not be the zero vector")
    return v


class PointLight(_Model):
    type: Literal["point"]
    position: Vec3
    power: Power  # total flux, emitted uniformly over the sphere of directions


class SpotLight(_Model):
    type: Literal["spot"]
    position: Vec3
    direction: Vec3
    cone_angle: Annotated[float, Field(strict=True, gt=0.0, le=90.0, allow_inf_nan=False)]  # half-angle, degrees
    power: Power  # total flux, uniform in solid angle inside the cone

    _direction = field_validator("direction")(_nonzero_direction)


class DirectionalLight(_Model):
    """Zero solid angle: photons leave a disc that covers the scene's bounding sphere."""

    type: Literal["directional"]
    direction: Vec3  # direction of travel of the light
    irradiance: Power  # W/m^2 on a surface perpendicular to `direction`

    _direction = field_validator("direction")(_nonzero_direction)


# A rotation (or a reflection): three orthonormal rows. Tolerance: what six decimal places keep.
Rotation = tuple[Vec3, Vec3, Vec3]
IDENTITY_ROTATION: Rotation = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
ROTATION_TOLERANCE = 1e-5
MIN_ENV_SIZE = (3, 2)  # an environment map's rows and columns at least (as Mitsuba's envmap)


def check_env_pixels(pixels: Pixels, field: str) -> None:
    """An environment map's image: at least MIN_ENV_SIZE, no negative sample."""
    rows, columns = pixels.height, pixels.width
    if rows < MIN_ENV_SIZE[0] or columns < MIN_ENV_SIZE[1]:
        raise SceneError(field, f"an environment map needs at least {MIN_ENV_SIZE[1]}x{MIN_ENV_SIZE[0]} pixels, "
                                f"not {columns}x{rows}")
    if (pixels.array < 0).any():
        raise SceneError(field, "an environment map's samples must not be negative")


class EnvironmentLight(_Model):
    """Light arriving from infinitely far in every direction: a constant `radiance`, or a
    latitude-longitude `map` (the name of a bitmap among the scene's textures, read as Mitsuba's
    envmap reads it: its rows from the local +y pole down to -y, its columns around y), times
    `scale`. `to_world` turns the map's local frame into the scene's (Mitsuba's envmap
    `to_world`, its linear part)."""

    type: Literal["environment"]
    radiance: Power | None = None
    map: Annotated[str, Field(min_length=1, max_length=MAX_PATH_CHARS)] | None = None
    scale: NonNeg = 1.0
    to_world: Rotation = IDENTITY_ROTATION

    @model_validator(mode="after")
    def _check(self) -> EnvironmentLight:
        if (self.radiance is None) == (self.map is None):
            raise ValueError("give either radiance or map")
        return self

    @field_validator("to_world")
    @classmethod
    def _rotation(cls, rows: Rotation) -> Rotation:
        m = np.array(rows, np.float64)
        if not np.allclose(m @ m.T, np.eye(3), atol=ROTATION_TOLERANCE):
            raise ValueError("must be a rotation: orthonormal rows (no scale or shear)")
        return rows


Light = Annotated[PointLight | SpotLight | DirectionalLight | EnvironmentLight, Field(discriminator="type")]


# ------------------------------------------------------------------------------ scene
class Scene(_Model):
    description: str = Field(default="", max_length=500)
    camera: Camera
    materials: dict[str, Material]
    shapes: list[Shape] = Field(max_length=MAX_SHAPES)
    lights: list[Light] = Field(default_factory=list, max_length=MAX_LIGHTS)
    textures: dict[str, Texture] = Field(default_factory=dict, max_length=MAX_TEXTURES)

    @model_validator(mode="after")
    def _check(self) -> Scene:
        texels = 0
        for name, texture in self.textures.items():
            if isinstance(texture, Bitmap) and texture.pixels is not None:
                texels += texture.pixels.array.size
                if texels > LOAD_LIMITS["texels"]:
                    raise SceneError(f"textures.{name}.pixels", f"the scene's images hold more than "
                                                                 f"{LOAD_LIMITS['texels']} samples")
        for name, material in self.materials.items():
            for key, value in material:
                if isinstance(value, TextureRef) and value.texture not in self.textures:
                    raise SceneError(f"materials.{name}.{key}.texture", f"unknown texture {value.texture!r}")
        for i, shape in enumerate(self.shapes):
            if shape.material not in self.materials:
                raise SceneError(f"shapes.{i}.material", f"unknown material {shape.material!r}")
        self._check_environment()
        return self

    def _check_environment(self) -> None:
        """At most one environment light; its map a bitmap of `textures` with non-negative
        samples, at least MIN_ENV_SIZE, and none of a texture's lookup fields."""
        found = [i for i, light in enumerate(self.lights) if isinstance(light, EnvironmentLight)]
        if len(found) > 1:
            raise SceneError(f"lights.{found[1]}", "a scene has at most one environment light")
        for i in found:
            light = self.lights[i]
            assert isinstance(light, EnvironmentLight)
            if light.map is None:
                continue
            texture = self.textures.get(light.map)
            if not isinstance(texture, Bitmap):
                raise SceneError(f"lights.{i}.map", f"{light.map!r} is not a bitmap of the scene's textures")
            for name in ("filter", "wrap_mode", "to_uv"):
                if getattr(texture, name) != Bitmap.model_fields[name].default:
                    raise SceneError(f"textures.{light.map}.{name}", f"an environment map's bitmap takes no {name} "
                                     "(it is read as Mitsuba's envmap: bilinear, wrapping around)")
            if texture.pixels is not None:  # (a file is checked once it is read)
                check_env_pixels(texture.pixels, f"textures.{light.map}.pixels")


# ------------------------------------------------------------------------ triangulation
@dataclass(frozen=True)
class ShapeGeometry:
    """A shape as triangles, with per-corner shading normals where the mesh has them and
    per-corner texture coordinates."""

    triangles: np.ndarray  # (n, 3, 3) float64
    normals: np.ndarray | None  # (n, 3, 3) float64, unit length, or None (flat)
    uvs: np.ndarray | None = None  # (n, 3, 2) float64, or None: (0, 0), (1, 0), (0, 1) (barycentric)


@contextmanager
def collector_paused() -> Iterator[None]:
    """Pause Python's cyclic garbage collector while a large mesh's rows are JSON's lists (made
    to encode a scene, or read from its text): a million small lists, every few hundred of
    which would start a collection pass over all the others (they hold no cycles; reference
    counting frees them)."""
    enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if enabled:
            gc.enable()


def inline_meshes(scene: Scene, base_dir: Path, root: Path = SCENES_DIR, budget: LoadBudget | None = None) -> dict:
    """The scene as JSON with every mesh file replaced by its triangles (and normals) and
    every image file by its pixels, so that a worker on any machine renders it with no file
    at hand. Also runs the checks that need the geometry (mesh paths, triangle limit,
    zero-area emitters)."""
    budget = budget or LoadBudget()
    geometry = shape_geometry(scene, base_dir, root, budget)
    data = scene.model_dump(mode="json", exclude_none=True)
    for i, shape in enumerate(scene.shapes):
        if isinstance(shape, Mesh) and shape.file is not None:
            geo = geometry[i]
            assert geo is not None
            entry = data["shapes"][i]
            del entry["file"]
            entry["vertices"] = geo.triangles.reshape(-1, 3).tolist()
            entry["triangles"] = np.arange(3 * len(geo.triangles)).reshape(-1, 3).tolist()
            if geo.normals is not None:
                entry["normals"] = geo.normals.reshape(-1, 3).tolist()
            if geo.uvs is not None:
                entry["uvs"] = geo.uvs.reshape(-1, 2).tolist()
    root = root.resolve()
    for name, texture in scene.textures.items():
        if isinstance(texture, Bitmap) and texture.file is not None:
            field = f"textures.{name}.file"
            path = scene_path(texture.file, field, base_dir, root, IMAGE_SUFFIXES, "image")
            entry = data["textures"][name]
            del entry["file"]
            entry["pixels"] = read_texture(path, budget, field).model_dump()
    return data


def names_files(scene: Scene) -> bool:
    """Whether the scene names a mesh or image file (to read and inline before it is sent)."""
    return (any(isinstance(shape, Mesh) and shape.file is not None for shape in scene.shapes)
            or any(isinstance(t, Bitmap) and t.file is not None for t in scene.textures.values()))


def inline_json(scene: Scene, base_dir: Path, root: Path = SCENES_DIR, budget: LoadBudget | None = None) -> str:
    """`inline_meshes` as JSON text; a scene with no mesh file to inline (the checks still
    run) goes through pydantic's own encoder, about twice as fast for large meshes."""
    with collector_paused():
        if names_files(scene):
            return json.dumps(inline_meshes(scene, base_dir, root, budget))
        shape_geometry(scene, base_dir, root, budget, shading=False)
        return scene.model_dump_json(exclude_none=True)


def read_mesh(path: Path, budget: LoadBudget, field: str, at: str = "") -> MeshData:
    """A mesh file read within the budget: its declared vertices and triangles are checked
    before it is parsed (parsing is what costs), its real triangles counted after."""
    data = budget.read(path, "mesh files", field, at)
    vertices, triangles = declared_counts(path.suffix, data)
    budget.check("mesh vertices", vertices, field, at)
    budget.check("triangles", triangles, field, at)
    mesh = load_mesh(path, data)
    budget.take("mesh vertices", len(mesh.vertices), field, at)
    budget.take("triangles", len(mesh.triangles), field, at)
    return mesh


def scene_path(name: str, field: str, base_dir: Path, root: Path, suffixes: tuple[str, ...], kind: str) -> Path:
    """The file a scene names (`kind`: "mesh", "image"), relative to `base_dir`: it must
    exist, lie inside `root` and have one of `suffixes`."""
    try:
        path = (base_dir / name).resolve()
    except (OSError, ValueError):
        raise SceneError(field, f"{kind} file {name!r} not found") from None
    if not path.is_relative_to(root):
        raise SceneError(field, f"{kind} path leaves the scene's directory")
    if path.suffix.lower() not in suffixes:
        raise SceneError(field, f"{kind} file {name!r} is not one of {', '.join(suffixes)}")
    try:
        found = path.is_file()
    except (OSError, ValueError):  # a name the file system refuses (too long in bytes, ...)
        found = False
    if not found:
        raise SceneError(field, f"{kind} file {name!r} not found")
    return path


def _mesh_data(shape: Mesh, field: str, base_dir: Path, root: Path, budget: LoadBudget) -> MeshData:
    """The mesh of a shape: its file (confined to `root`) or its inline arrays."""
    if shape.file is None:
        assert shape.vertices is not None and shape.triangles is not None  # Mesh._check: one source or the other
        try:
            return check_mesh(shape.vertices, shape.triangles, shape.normals, shape.uvs)
        except MeshError as exc:
            raise SceneError(field, str(exc)) from None
    path = scene_path(shape.file, f"{field}.file", base_dir, root, MESH_SUFFIXES, "mesh")
    try:
        return read_mesh(path, budget, f"{field}.file")
    except OSError as exc:
        raise SceneError(f"{field}.file", f"cannot read mesh file {shape.file!r}: {exc.strerror or exc}") from None
    except MeshError as exc:
        raise SceneError(f"{field}.file", f"{shape.file}: {exc}") from None


def read_texture(path: Path, budget: LoadBudget, field: str, at: str = "") -> Pixels:
    """An image file read within the budget: its declared size is checked before it is
    decoded (decoding is what costs)."""
    try:
        budget.take("image files", 1, field, at)
        budget.take("bytes", path.stat().st_size, field, at)
        height, width, channels = image_shape(path)
        budget.take("texels", height * width * channels, field, at)
        return Pixels.of(read_image(path))
    except OSError as exc:
        raise SceneError(field, f"{at + ': ' if at else ''}cannot read {path.name}: {exc.strerror or exc}") from None
    except ImageError as exc:
        raise SceneError(field, f"{at + ': ' if at else ''}{path.name}: {exc}") from None


def _corner_normals(mesh: MeshData) -> np.ndarray | None:
    """Unit per-corner normals; corners whose normal is zero take their face's normal."""
    if mesh.normals is None:
        return None
    n = mesh.normals[mesh.triangles]
    tris = mesh.vertices[mesh.triangles]
    face = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    length = np.linalg.norm(n, axis=2, keepdims=True)
    n = np.where(length > 1e-12, n / np.maximum(length, 1e-300), face[:, None, :])
    return n / np.maximum(np.linalg.norm(n, axis=2, keepdims=True), 1e-300)


def shape_geometry(scene: Scene, base_dir: Path, root: Path = SCENES_DIR, budget: LoadBudget | None = None,
                   shading: bool = True) -> list[ShapeGeometry | None]:
    """Per shape, its triangles and shading normals (None for spheres; no normals at all
    without `shading`, for a caller that only wants the checks).

    Mesh files are resolved relative to `base_dir` and must lie inside `root` (the scene
    file's folder for the CLI, the upload for the service): a scene can never make the
    renderer read an arbitrary file. Files are read within `budget` (a new one if none).
    """
    budget = budget or LoadBudget()
    out: list[ShapeGeometry | None] = []
    total = 0
    root = root.resolve()
    for i, shape in enumerate(scene.shapes):
        if isinstance(shape, Sphere):
            out.append(None)
            continue
        normals = uvs = None
        if isinstance(shape, Quad):
            c, e1, e2 = (np.array(x, dtype=np.float64) for x in (shape.corner, shape.edge1, shape.edge2))
            tris = np.array([[c, c + e1, c + e1 + e2], [c, c + e1 + e2, c + e2]])
            uvs = np.array(shape.uvs or QUAD_UVS, np.float64)[[[0, 1, 2], [0, 2, 3]]]
        else:
            mesh = _mesh_data(shape, f"shapes.{i}", base_dir, root, budget)
            tris = mesh.vertices[mesh.triangles]
            normals = _corner_normals(mesh) if shading else None
            uvs = mesh.uvs[mesh.triangles] if mesh.uvs is not None else None
        total += len(tris)
        if total > MAX_TRIANGLES:
            raise SceneError(f"shapes.{i}", f"scene has more than {MAX_TRIANGLES} triangles")
        if np.abs(tris).max(initial=0.0) > MAX_COORD:
            raise SceneError(f"shapes.{i}", f"a coordinate exceeds {MAX_COORD:g}")
        if shape.emission is not None and max(shape.emission) > 0.0:
            area = 0.5 * np.linalg.norm(np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]), axis=1).sum()
            if not area > 0.0:
                raise SceneError(f"shapes.{i}.emission", "an emitting shape must have non-zero area")
        out.append(ShapeGeometry(tris, normals, uvs))
    return out


def shape_triangles(scene: Scene, base_dir: Path, root: Path = SCENES_DIR) -> list[np.ndarray | None]:
    """Per shape, its triangles as an (n, 3, 3) array (None for spheres)."""
    return [None if g is None else g.triangles for g in shape_geometry(scene, base_dir, root)]


_UNION_TAGS = {
    "materials": {"diffuse", "mirror", "glass", "rough_glass", "thin_glass", "glossy", "conductor", "rough_conductor",
                  "plastic", "rough_plastic"},
    "shapes": {"sphere", "quad", "mesh"},
    "lights": {"point", "spot", "directional", "environment"},
    "textures": {"bitmap", "checkerboard"},
}


def _field_path(loc: tuple) -> str:
    return ".".join(str(p) for p in loc)


def parse_scene(data: object) -> Scene:
    """Validate a scene given as parsed JSON, raising SceneError naming the field."""
    try:
        scene = Scene.model_validate(data)
    except ValidationError as exc:
        err = exc.errors()[0]
        ctx_err = err.get("ctx", {}).get("error")
        if isinstance(ctx_err, SceneError):
            raise ctx_err from None
        loc = list(err["loc"])
        # A discriminated union puts the tag after the list index or dict key: drop it.
        if len(loc) >= 3 and loc[0] in _UNION_TAGS and loc[2] in _UNION_TAGS[loc[0]]:
            del loc[2]
        loc = loc[:2] + [p for p in loc[2:] if p not in (CONSTANT, REFERENCE)]  # a colour's tag too
        raise SceneError(_field_path(tuple(loc)), err["msg"]) from None
    return scene


def load_scene_file(path: Path | str, budget: LoadBudget | None = None) -> tuple[Scene, Path]:
    """Read and validate a scene file; returns the scene and its directory (for meshes)."""
    path = Path(path)
    try:
        data = json.loads((budget or LoadBudget()).read(path, "scene files", path.name))
    except FileNotFoundError:
        raise SceneError("", f"scene file {str(path)!r} not found") from None
    except OSError as exc:
        raise SceneError("", f"cannot read scene file {str(path)!r}: {exc.strerror or exc}") from None
    except RecursionError:
        raise SceneError("", f"{path.name} is not valid JSON: nested too deeply") from None
    except ValueError as exc:  # not JSON, not UTF-8, or an integer past Python's digit limit
        raise SceneError("", f"{path.name} is not valid JSON: {exc}") from None
    return parse_scene(data), path.resolve().parent


def bundled_scene_names() -> list[str]:
    """The names of the scenes in scenes/, the only names a scene may be asked for by."""
    return sorted(p.stem for p in SCENES_DIR.glob("*.json") if re.match(SCENE_NAME_PATTERN, p.stem))


def load_any_scene(path: Path | str, params: dict[str, str] | None = None, root: Path | None = None,
                   budget: LoadBudget | None = None, notes: list[str] | None = None) -> tuple[Scene, Path]:
    """A scene from our JSON or a Mitsuba 3 XML file (by suffix), and its directory.

    The scene comes back self-contained: every mesh file it names is read now, confined
    to `root` (default: the scene file's folder; the service passes its upload), and
    inlined, so it renders wherever it is sent. `params` override the XML's <default>s.
    Everything is read within one `budget` (a new one if none). What a Mitsuba scene holds
    that was accepted but ignored is appended to `notes` ("ignored: ...", one line each)."""
    path = Path(path)
    base_dir = path.resolve().parent
    budget = budget or LoadBudget()
    if path.suffix.lower() == ".xml":
        from worker.mitsuba_scene import convert_and_validate  # it builds on this module

        _, scene, found = convert_and_validate(path, params, root, budget)
        if notes is not None:
            notes.extend(found)
        return scene, base_dir
    if params:
        raise SceneError("params", "parameters apply to Mitsuba XML scenes only")
    scene, base_dir = load_scene_file(path, budget)
    if names_files(scene):
        with collector_paused():
            scene = parse_scene(inline_meshes(scene, base_dir, root or base_dir, budget))
    return scene, base_dir


def scene_file(text: str) -> Path | None:
    """A scene named on a command line: a scene file by path (.json, or Mitsuba .xml), or None
    for a bundled scene's name; an existing file of another kind is a SceneError (not a name)."""
    path = Path(text)
    if path.suffix.lower() in (".json", ".xml"):
        return path
    if path.exists():
        raise SceneError("scene", f"{text}: a scene file is .json (photonfarm's) or .xml (Mitsuba 3)")
    return None


def bundled_scene_path(name: str) -> Path:
    """The file of a bundled scene, by name (e.g. 'cornell-box'). The name is looked up
    among the bundled scenes, never joined into a path, so no name reads another file."""
    names = bundled_scene_names()
    if name not in names:
        shown = name if len(name) <= MAX_SCENE_NAME else name[:MAX_SCENE_NAME] + "..."
        raise SceneError("scene", f"no bundled scene {shown!r} (have: {', '.join(names)})")
    return SCENES_DIR / f"{name}.json"
