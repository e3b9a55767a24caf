"""Images out: linear float EXR and tone-mapped sRGB PNG, through OpenImageIO."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import OpenImageIO as oiio


def tonemap(rgb: np.ndarray, exposure: float = 1.0) -> np.ndarray:
    """Linear radiance -> 8-bit sRGB: x -> 1 - exp(-exposure x) (as smallppm), then the sRGB curve."""
    x = 1.0 - np.exp(-exposure * np.clip(np.nan_to_num(rgb, nan=0.0, posinf=1e30), 0.0, None))
    srgb = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1.0 / 2.4) - 0.055)
    return np.clip(np.round(srgb * 255.0), 0, 255).astype(np.uint8)


def write_image(path: Path | str, rgb: np.ndarray) -> None:
    """Write an (H, W, 3) linear image: .exr as float32, .png tone-mapped."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".exr":
        pixels = np.ascontiguousarray(rgb, np.float32)
        spec = oiio.ImageSpec(pixels.shape[1], pixels.shape[0], 3, oiio.FLOAT)
        spec.attribute("compression", "zip")
    elif suffix == ".png":
        pixels = tonemap(rgb)
        spec = oiio.ImageSpec(pixels.shape[1], pixels.shape[0], 3, oiio.UINT8)
    else:
        raise ValueError(f"unsupported image format {suffix!r}: use .exr or .png")
    out = oiio.ImageOutput.create(str(path))
    if out is None or not out.open(str(path), spec):
        raise OSError(f"cannot write {path}: {oiio.geterror()}")
    try:
        if not out.write_image(pixels):
            raise OSError(f"cannot write {path}: {out.geterror()}")
    finally:
        out.close()


def read_image(path: Path | str) -> np.ndarray:
    """Read an image as (H, W, channels) float32."""
    buf = oiio.ImageBuf(str(path))
    if buf.has_error:
        raise OSError(f"cannot read {path}: {buf.geterror()}")
    return buf.get_pixels(oiio.FLOAT)
