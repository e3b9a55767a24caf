"""Surface records: each shape's material and emission as the kernels read them
(kernels/materials.cl, its row layout), and the constants a plastic coat needs, computed
here once per scene; and the scene's textures as the kernels read them (kernels/textures.cl).

Plastics follow Mitsuba 3's definitions: the diffuse base is divided by 1 - R_int, R_int the
coat's internal diffuse reflectance, 2 * integral of F(mu, 1/eta) mu dmu over [0, 1] for a
smooth coat (the cosine-weighted mean of the Fresnel reflectance seen from inside), and for a rough coat
the mean of R(mu, 1/eta) mu over TABLE_SIZE evenly spaced cosines, times 2, R the rough
dielectric's reflectance; a rough coat's transmittance T(mu) from outside is tabulated at the
same cosines. Both integrals are over microfacet normals h drawn by D(h) cos_h (Walter et al.
2007): R or T = E[F_or_(1-F) G1(wi) G1(wo) (wi.h) / (mu cos_h)], by Gauss-Legendre quadrature.
"""

from __future__ import annotations

import math

import numpy as np

from kernels.contract import (
    MATERIAL_FLAGS,
    MATERIALS,
    SURF_ROWS,
    TABLE_SIZE,
    TEX_ALIGN,
    TEX_ROWS,
    TEXTURE_FLAGS,
    TEXTURE_KINDS,
    WRAP_MODES,
)
from worker.images import linear_values
from worker.scene import (
    Bitmap,
    Conductor,
    Glass,
    Glossy,
    Mirror,
    Plastic,
    RoughConductor,
    RoughGlass,
    RoughPlastic,
    Scene,
    TextureRef,
    ThinGlass,
)

QUADRATURE = 96  # Gauss-Legendre nodes per dimension of the microfacet integrals


def int_bits(values: np.ndarray | list[int]) -> np.ndarray:
    """int32 values as the float32 with the same bits (how records carry integers)."""
    return np.asarray(values, np.int32).view(np.float32)


def fresnel(cos_i: np.ndarray, eta: float) -> np.ndarray:
    """Unpolarised dielectric reflectance at cos_i > 0, eta = far side / this side (1 under
    total internal reflection)."""
    sin2_t = (1.0 - cos_i ** 2) / eta ** 2
    cos_t = np.sqrt(np.clip(1.0 - sin2_t, 0.0, None))
    with np.errstate(invalid="ignore"):  # 0 / 0 at grazing total internal reflection, replaced below
        rs = (cos_i - eta * cos_t) / (cos_i + eta * cos_t)
        rp = (eta * cos_i - cos_t) / (eta * cos_i + cos_t)
    return np.where(sin2_t >= 1.0, 1.0, 0.5 * (rs ** 2 + rp ** 2))


def smith_g1(cos_v: np.ndarray, cos_vh: np.ndarray, alpha: float, beckmann: bool) -> np.ndarray:
    """Smith masking of one direction (kernels/materials.cl, mf_g1)."""
    tan2 = np.clip(1.0 - cos_v ** 2, 0.0, None) / np.maximum(cos_v ** 2, 1e-30)
    if beckmann:
        b = 1.0 / (alpha * np.sqrt(np.maximum(tan2, 1e-30)))  # tan 0: b far past 1.6, so 1
        g = np.where(b >= 1.6, 1.0, (3.535 * b + 2.181 * b * b) / (1.0 + 2.276 * b + 2.577 * b * b))
    else:
        g = 2.0 / (1.0 + np.sqrt(1.0 + alpha ** 2 * tan2))
    return np.where(cos_vh * cos_v > 0.0, g, 0.0)


def rough_dielectric_albedo(mu: np.ndarray, eta: float, alpha: float, beckmann: bool,
                            transmit: bool) -> np.ndarray:
    """The rough dielectric interface's reflectance (or transmittance) for light arriving at
    cos mu from the side where the relative index is eta."""
    x, w = np.polynomial.legendre.leggauss(QUADRATURE)
    u, wu = 0.5 * (x + 1.0), 0.5 * w
    phi, wphi = math.pi * (x + 1.0), math.pi * w
    # Microfacet normals by D(h) cos_h: tan^2 = -a^2 ln(1 - u) (Beckmann), a^2 u / (1 - u) (GGX).
    tan2 = -alpha ** 2 * np.log1p(-u) if beckmann else alpha ** 2 * u / (1.0 - u)
    cos_h = 1.0 / np.sqrt(1.0 + tan2)
    sin_h = np.sqrt(1.0 - cos_h ** 2)
    h = np.stack(np.broadcast_arrays(sin_h[:, None] * np.cos(phi)[None, :], sin_h[:, None] * np.sin(phi)[None, :],
                                     cos_h[:, None]), axis=-1)  # (u, phi, 3)
    weight = wu[:, None] * wphi[None, :] / (2.0 * math.pi)  # the phi integral is an average
    mu = np.maximum(np.asarray(mu, np.float64), 1e-6)
    out = np.empty(mu.shape)
    for i, m in enumerate(mu.flat):
        wi = np.array([math.sqrt(max(0.0, 1.0 - m * m)), 0.0, m])
        ih = h @ wi
        f = fresnel(np.clip(ih, 1e-12, 1.0), eta)
        if transmit:
            # Refraction about h: wt = -wi / eta + (ih / eta - cos_t) h, cos_t from Snell's law.
            cos_t = np.sqrt(np.clip(1.0 - (1.0 - ih ** 2) / eta ** 2, 0.0, None))
            wo = -wi / eta + (ih / eta - cos_t)[..., None] * h
            share = 1.0 - f
        else:
            wo = 2.0 * ih[..., None] * h - wi
            share = f
        oh, oz = np.einsum("...k,...k->...", wo, h), wo[..., 2]
        g = smith_g1(np.full_like(ih, m), ih, alpha, beckmann) * smith_g1(oz, oh, alpha, beckmann)
        value = np.where(ih > 0.0, share * g * ih / (m * cos_h[:, None]), 0.0)
        out.flat[i] = float(np.sum(weight * value))
    return out


def table_cosines() -> np.ndarray:
    return np.linspace(0.0, 1.0, TABLE_SIZE)


def coat_constants(material: Plastic) -> tuple[float, np.ndarray | None]:
    """(R_int, the transmittance table or None) of a plastic's coat."""
    eta = material.ior
    if not isinstance(material, RoughPlastic):
        # Inside, below the critical cosine mu_c every ray is reflected (F = 1): R_int =
        # mu_c^2 + 2 * integral over [mu_c, 1] of F mu, the smooth rest by Gauss-Legendre.
        mu_c = math.sqrt(max(0.0, 1.0 - 1.0 / eta ** 2))
        x, w = np.polynomial.legendre.leggauss(QUADRATURE)
        mu = mu_c + 0.5 * (x + 1.0) * (1.0 - mu_c)
        rest = float(np.sum(0.5 * (1.0 - mu_c) * w * fresnel(mu, 1.0 / eta) * mu))
        return mu_c ** 2 + 2.0 * rest, None
    beckmann = material.distribution == "beckmann"
    mu = table_cosines()
    internal = rough_dielectric_albedo(mu, 1.0 / eta, material.alpha, beckmann, transmit=False)
    table = rough_dielectric_albedo(mu, eta, material.alpha, beckmann, transmit=True)
    return float(np.mean(internal * np.maximum(mu, 1e-6)) * 2.0), table


def used_textures(scene: Scene) -> list[str]:
    """The names of the textures the scene's materials refer to, in the order of their
    records (texture_table)."""
    names = {value.texture for material in scene.materials.values() for _, value in material
             if isinstance(value, TextureRef)}
    return [name for name in scene.textures if name in names]


def texture_texels(scene: Scene, name: str) -> np.ndarray:
    """A texture's values, (height, width, 1 or 3) linear float32 clamped to [0, 1] (texture
    values are reflectances or roughnesses); a checkerboard's are its two colours, (1, 2, 3)."""
    texture = scene.textures[name]
    if isinstance(texture, Bitmap):
        assert texture.pixels is not None  # files are inlined when the scene is loaded
        values = _value_channels(texture.pixels.linear(texture.raw))
    else:
        values = np.array([[texture.color0, texture.color1]], np.float32)
    return np.clip(values, 0.0, 1.0).astype(np.float32)


def _value_channels(samples: np.ndarray) -> np.ndarray:
    """The channels of (height, width, channels) samples that hold a texture's value: grey's
    one, or rgb (alpha is not a colour)."""
    return samples[..., :1] if samples.shape[2] <= 2 else samples[..., :3]


def _texel_data(scene: Scene, name: str) -> tuple[np.ndarray, int, int, int]:
    """A texture's bytes in tex_texels, its format flags, width and height (kernels/textures.cl):
    an 8-bit bitmap's decode table (256 float32, each byte's linear value rounded to a half
    float, as Mitsuba 3 keeps 8-bit images) then its bytes, TEX_BYTES; any other texture's
    linear values as half floats. TEX_GREY for one channel, else rgb padded to 4 channels;
    row-major from the top row."""
    texture = scene.textures[name]
    table = np.zeros(0, np.uint8)
    if isinstance(texture, Bitmap) and texture.pixels is not None and texture.pixels.sample == "uint8":
        samples = _value_channels(texture.pixels.array)
        decoded = linear_values(np.arange(256, dtype=np.uint8), texture.raw).astype(np.float16)
        table, flags = decoded.astype(np.float32).view(np.uint8), TEXTURE_FLAGS["bytes"]
    else:
        samples, flags = texture_texels(scene, name).astype(np.float16), 0
    height, width, channels = samples.shape
    if channels == 3:
        samples = np.pad(samples, ((0, 0), (0, 0), (0, 1)))
    else:
        flags |= TEXTURE_FLAGS["grey"]
    return np.concatenate([table, samples.view(np.uint8).ravel()]), flags, width, height


def texture_table(scene: Scene) -> tuple[np.ndarray, np.ndarray]:
    """The used textures on the device (kernels/textures.cl): (TEX_ROWS * textures, 4) float32
    records and every texture's texels in one byte array (_texel_data), each texture's from a
    multiple of TEX_ALIGN bytes."""
    names = used_textures(scene)
    records = np.zeros((TEX_ROWS * len(names), 4), np.float32)
    chunks: list[np.ndarray] = []
    offset = 0
    for i, name in enumerate(names):
        texture = scene.textures[name]
        data, flags, width, height = _texel_data(scene, name)
        flags |= TEXTURE_KINDS[texture.type]
        if isinstance(texture, Bitmap):
            flags |= WRAP_MODES[texture.wrap_mode] << 2
            flags |= TEXTURE_FLAGS["nearest"] if texture.filter == "nearest" else 0
        rows = records[TEX_ROWS * i:TEX_ROWS * (i + 1)]
        rows[0] = int_bits([flags, offset, width, height])
        rows[1, :3], rows[2, :3] = texture.to_uv
        chunks.append(np.pad(data, (0, -data.size % TEX_ALIGN)))
        offset += chunks[-1].size
    return records, np.concatenate(chunks) if chunks else np.zeros(0, np.uint8)


def _mean(scene: Scene, value: tuple[float, float, float] | TextureRef) -> float:
    """The mean of a colour over its channels (a texture's: over its texels too)."""
    return float(np.mean(texture_texels(scene, value.texture) if isinstance(value, TextureRef) else value))


def surface_records(scene: Scene) -> np.ndarray:
    """(SURF_ROWS * shapes + table rows, 4) float32: every shape's record, then the tables."""
    records = np.zeros((SURF_ROWS * len(scene.shapes), 4), np.float32)
    tables: list[np.ndarray] = []
    texture_index = {name: i for i, name in enumerate(used_textures(scene))}

    def colour(value: tuple[float, float, float] | TextureRef) -> tuple[float, float, float]:
        return (0.0, 0.0, 0.0) if isinstance(value, TextureRef) else value

    def scalar(value: float | TextureRef) -> float:
        return 0.0 if isinstance(value, TextureRef) else value

    for i, shape in enumerate(scene.shapes):
        material = scene.materials[shape.material]
        rows = records[SURF_ROWS * i:SURF_ROWS * (i + 1)]
        rows[1, :3] = shape.emission or (0.0, 0.0, 0.0)
        flags = 0
        # The textures row: the texture of row 0's colour, row 3's colour, the roughness and the opacity.
        slots: list[object] = [None, None, None]
        if isinstance(material, Mirror | Conductor | RoughConductor):
            kind = "rough_conductor" if isinstance(material, RoughConductor) else "conductor"
            slots[0] = material.albedo if isinstance(material, Mirror) else material.specular
            rows[0, :3] = colour(material.albedo if isinstance(material, Mirror) else material.specular)
            eta, k = (None, None) if isinstance(material, Mirror) else (material.eta, material.k)
            if eta is None or k is None:
                flags |= MATERIAL_FLAGS["no_fresnel"]
            else:
                rows[2, :3], rows[3, :3] = eta, k
            if isinstance(material, RoughConductor):
                rows[1, 3] = scalar(material.alpha)
                slots[2] = material.alpha
                flags |= MATERIAL_FLAGS["beckmann"] if material.distribution == "beckmann" else 0
        elif isinstance(material, Glass | ThinGlass):
            kind = "thin_glass" if isinstance(material, ThinGlass) else "rough_glass" if isinstance(
                material, RoughGlass) else "glass"
            if isinstance(material, RoughGlass):
                rows[1, 3] = scalar(material.alpha)
                slots[2] = material.alpha
                flags |= MATERIAL_FLAGS["beckmann"] if material.distribution == "beckmann" else 0
            transmittance = material.albedo if material.transmittance is None else material.transmittance
            rows[0, :3], rows[3, :3] = colour(material.albedo), colour(transmittance)
            slots[0], slots[1] = material.albedo, transmittance
            rows[2, 0] = material.ior
        elif isinstance(material, Plastic):
            kind = "rough_plastic" if isinstance(material, RoughPlastic) else "plastic"
            internal, table = coat_constants(material)
            # The specular sampling weight from the colours' means (textures: over their texels), as Mitsuba 3's.
            d_mean, s_mean = _mean(scene, material.albedo), _mean(scene, material.specular)
            rows[0, :3], rows[3, :3] = colour(material.albedo), colour(material.specular)
            slots[0], slots[1] = material.albedo, material.specular
            rows[2, :3] = (material.ior, internal, s_mean / (d_mean + s_mean) if d_mean + s_mean > 0 else 0.5)
            flags |= MATERIAL_FLAGS["nonlinear"] if material.nonlinear else 0
            if isinstance(material, RoughPlastic):
                rows[1, 3] = material.alpha
                flags |= MATERIAL_FLAGS["beckmann"] if material.distribution == "beckmann" else 0
                assert table is not None
                rows[3, 3] = int_bits([len(records) + sum(len(t) for t in tables)])[0]
                tables.append(table.astype(np.float32).reshape(-1, 4))
        elif isinstance(material, Glossy):
            kind = "glossy"
            rows[0, :3] = colour(material.albedo)
            slots[0] = material.albedo
            rows[1, 3] = material.exponent
        else:
            kind = "diffuse"
            rows[0, :3] = colour(material.albedo)
            slots[0] = material.albedo
        # The opacity (Mitsuba's mask): its row, or its texture in the textures row.
        slots.append(material.opacity)
        if material.opacity != 1.0:
            flags |= MATERIAL_FLAGS["masked"]
        rows[5, 0] = 1.0 if isinstance(material.opacity, TextureRef) else material.opacity
        textures = [texture_index[v.texture] if isinstance(v, TextureRef) else -1 for v in slots]
        if max(textures) >= 0:
            flags |= MATERIAL_FLAGS["textured"]
        rows[4] = int_bits(textures)
        rows[0, 3] = int_bits([MATERIALS[kind]])[0]
        rows[2, 3] = int_bits([flags])[0]
    return np.concatenate([records, *tables]) if tables else records
