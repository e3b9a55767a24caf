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


# Error-map colours from relative error 0.1% (blue) through 1%, 10% to 100% and above (red).
_ERROR_STOPS = np.log10([1e-3, 1e-2, 1e-1, 1.0])
_ERROR_COLOURS = np.array([[0.15, 0.25, 0.85], [0.1, 0.75, 0.3], [0.95, 0.85, 0.1], [0.9, 0.1, 0.1]])


def error_colours(relative: np.ndarray, measured: np.ndarray) -> np.ndarray:
    """Display colours (0..1) for a relative-error map on a log scale; unmeasured pixels black."""
    x = np.log10(np.clip(relative, 1e-3, 1.0))
    rgb = np.stack([np.interp(x, _ERROR_STOPS, _ERROR_COLOURS[:, c]) for c in range(3)], axis=-1)
    return np.where(measured[..., None], rgb, 0.0)


def write_image(path: Path | str, pixels_in: np.ndarray, channels: tuple[str, ...] | None = None,
                display: bool = False, metadata: dict[str, object] | None = None) -> None:
    """Write an (H, W, C) image. .exr: float32, linear, optionally named channels (a name
    "layer.channel" puts the channel in a layer of the same file) and `metadata` as
    "photonfarm:<key>" header attributes (strings). .png: 8-bit; linear radiance is
    tone-mapped unless `display` says it already is 0..1."""
    path = Path(path)
    suffix = path.suffix.lower()
    n_channels = pixels_in.shape[2]
    if suffix == ".exr":
        pixels = np.ascontiguousarray(pixels_in, np.float32)
        spec = oiio.ImageSpec(pixels.shape[1], pixels.shape[0], n_channels, oiio.FLOAT)
        spec.attribute("compression", "zip")
        if channels is not None:
            spec.channelnames = channels
        for key, value in (metadata or {}).items():
            spec.attribute(f"photonfarm:{key}", str(value))
    elif suffix == ".png":
        pixels = np.clip(np.round(pixels_in * 255.0), 0, 255).astype(np.uint8) if display else tonemap(pixels_in)
        spec = oiio.ImageSpec(pixels.shape[1], pixels.shape[0], n_channels, oiio.UINT8)
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


def _pixels(buf: oiio.ImageBuf, path: Path | str) -> np.ndarray:
    """The buffer's pixels as (H, W, channels) float32; OSError where OIIO reads none."""
    pixels = buf.get_pixels(oiio.FLOAT)
    if pixels is None:
        raise OSError(f"cannot read {path}: {buf.geterror()}")
    return pixels


def read_image(path: Path | str) -> np.ndarray:
    """Read an image as (H, W, channels) float32."""
    buf = oiio.ImageBuf(str(path))
    if buf.has_error:
        raise OSError(f"cannot read {path}: {buf.geterror()}")
    return _pixels(buf, path)


def read_channels(path: Path | str) -> dict[str, np.ndarray]:
    """An image's channels by name (EXR keeps them in alphabetical order, not written order)."""
    buf = oiio.ImageBuf(str(path))
    if buf.has_error:
        raise OSError(f"cannot read {path}: {buf.geterror()}")
    pixels = _pixels(buf, path)
    return {name: pixels[..., i] for i, name in enumerate(buf.spec().channelnames)}


def read_metadata(path: Path | str) -> dict[str, str]:
    """The "photonfarm:<key>" header attributes of an EXR written by write_image."""
    image = oiio.ImageInput.open(str(path))
    if image is None:
        raise OSError(f"cannot read {path}: {oiio.geterror()}")
    try:
        attribs = image.spec().extra_attribs
        return {a.name.split(":", 1)[1]: str(a.value) for a in attribs if a.name.startswith("photonfarm:")}
    finally:
        image.close()
