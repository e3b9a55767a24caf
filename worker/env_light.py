"""The environment light on the host: its radiance map and the sampling distribution over
it, as rows of the emitter table (layout and equations: kernels/environment.cl).

A map's samples are the grid points of a bilinear L (Mitsuba 3's envmap); its cells, W x
(H - 1), are sampled in proportion to their mean corner (the integral of the bilinear L over
the cell) times their solid angle (2 pi / W)(cos t_j - cos t_{j+1}), t_j = pi j / (H - 1).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from worker.images import IMAGE_SUFFIXES
from worker.scene import Bitmap, EnvironmentLight, LoadBudget, Scene, check_env_pixels, read_texture, scene_path


@dataclass(frozen=True)
class EnvMap:
    """An environment light's radiance: `texels` (H, W, 3) float64 radiance with `scale`
    applied, or None for a constant `radiance`; `to_world` its 3x3 rotation."""

    texels: np.ndarray | None
    radiance: np.ndarray
    to_world: np.ndarray

    def integral(self) -> np.ndarray:
        """int L dw over the sphere, rgb (the map's cells by their mean corner)."""
        if self.texels is None:
            return 4.0 * math.pi * self.radiance
        return np.einsum("jic,j->c", cell_means(self.texels), row_solid_angles(self.texels))

    def rows(self) -> np.ndarray:
        """The map's rows of the emitter table, (n, 4) float32: world-to-local rotation (w:
        W, H as int bits), samples, then the packed CDFs (a map's only: a constant has none)."""
        assert self.texels is not None
        h, w, _ = self.texels.shape
        head = np.zeros((3, 4), np.float32)
        head[:, :3] = self.to_world.T  # world-to-local rows: the rotation's inverse, its transpose
        head[:2, 3] = np.array([w, h], np.int32).view(np.float32)
        samples = np.zeros((h * w, 4), np.float32)
        samples[:, :3] = self.texels.reshape(-1, 3)
        marginal, conditional = cdfs(self.texels)
        packed = np.concatenate([marginal, conditional.ravel()])
        packed = np.concatenate([packed, np.zeros(-len(packed) % 4, np.float32)]).reshape(-1, 4)
        return np.concatenate([head, samples, packed])


def cell_means(texels: np.ndarray) -> np.ndarray:
    """(H - 1, W, 3): each cell's mean corner; cell (j, i) has corners at rows j, j + 1 and
    columns i, i + 1 (the last column's right neighbour is the first)."""
    right = np.roll(texels, -1, axis=1)
    corners = texels + right
    return 0.25 * (corners[:-1] + corners[1:])


def row_solid_angles(texels: np.ndarray) -> np.ndarray:
    """(H - 1,): the solid angle of one cell of each cell row."""
    h, w, _ = texels.shape
    cos_t = np.cos(np.pi * np.arange(h) / (h - 1))
    return 2.0 * np.pi / w * (cos_t[:-1] - cos_t[1:])


def cdfs(texels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The marginal CDF over cell rows (H - 1,) and each row's conditional CDF (H - 1, W),
    float32, each ending at exactly 1 (a row of zero weight: uniform, never chosen)."""
    weights = cell_means(texels).sum(axis=2) * row_solid_angles(texels)[:, None]
    rows = weights.sum(axis=1)
    marginal = (np.cumsum(rows) / rows.sum()).astype(np.float32)
    marginal[-1] = 1.0
    safe = np.where(rows[:, None] > 0.0, weights, 1.0)
    conditional = (np.cumsum(safe, axis=1) / safe.sum(axis=1, keepdims=True)).astype(np.float32)
    conditional[:, -1] = 1.0
    return marginal, conditional


def texel_rgb(linear: np.ndarray) -> np.ndarray:
    """(H, W, 3) from an image's linear channels: grey (and grey + alpha) to rgb, alpha dropped."""
    return np.repeat(linear[..., :1], 3, axis=2) if linear.shape[2] < 3 else linear[..., :3]


def env_map(scene: Scene, light: EnvironmentLight, base_dir: Path, root: Path) -> EnvMap:
    """The light's map read from the scene (its bitmap inline, or its file inside `root`)."""
    to_world = np.array(light.to_world, np.float64)
    if light.map is None:
        assert light.radiance is not None  # EnvironmentLight._check: one or the other
        return EnvMap(None, np.array(light.radiance, np.float64) * light.scale, to_world)
    texture = scene.textures[light.map]
    assert isinstance(texture, Bitmap)  # Scene._check_environment
    pixels = texture.pixels
    if pixels is None:
        assert texture.file is not None
        field = f"textures.{light.map}.file"
        path = scene_path(texture.file, field, base_dir, root.resolve(), IMAGE_SUFFIXES, "image")
        pixels = read_texture(path, LoadBudget(), field)
        check_env_pixels(pixels, field)
    texels = texel_rgb(pixels.linear(texture.raw)).astype(np.float64) * light.scale
    return EnvMap(texels, np.zeros(3), to_world)
