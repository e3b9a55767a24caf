"""Images in scenes (textures, environment maps): reading files with OpenImageIO, and the
inline form a scene carries them in so that it renders on any machine with no file at hand.

An image keeps the sample type its file stores (8- or 16-bit integers, half or single
floats): integer images are sRGB-encoded unless read raw (as Mitsuba's `bitmap` treats
them), float images are linear. `Pixels.linear` gives the linear float32 values.
"""

from __future__ import annotations

import base64
import binascii
import zlib
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
import OpenImageIO as oiio
from pydantic import BaseModel, ConfigDict, Field, PrivateAttr, model_validator

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".exr", ".hdr", ".tga", ".bmp", ".pfm", ".tif", ".tiff")
MAX_IMAGE_SIDE = 16384
SampleType = Literal["uint8", "uint16", "float16", "float32"]
_OIIO_TYPES: dict[str, SampleType] = {"uint8": "uint8", "uint16": "uint16", "half": "float16", "float": "float32"}


class ImageError(ValueError):
    """An image file or inline image that cannot be read (the caller adds the scene field)."""


class Pixels(BaseModel):
    """An image inline: `data` is base64 of the zlib-compressed samples, row-major
    (height, width, channels), little-endian, top row first."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    width: Annotated[int, Field(strict=True, ge=1, le=MAX_IMAGE_SIDE)]
    height: Annotated[int, Field(strict=True, ge=1, le=MAX_IMAGE_SIDE)]
    channels: Literal[1, 2, 3, 4]
    sample: SampleType
    data: str
    _array: np.ndarray = PrivateAttr()

    @model_validator(mode="after")
    def _decode(self) -> Pixels:
        dtype = np.dtype(self.sample).newbyteorder("<")
        size = self.width * self.height * self.channels * dtype.itemsize
        try:
            packed = base64.b64decode(self.data, validate=True)
            inflater = zlib.decompressobj()
            raw = inflater.decompress(packed, size + 1)  # never more than the image can hold
        except (binascii.Error, zlib.error) as exc:
            raise ValueError(f"data is not base64 of zlib-compressed samples: {exc}") from None
        if len(raw) != size or not inflater.eof:
            raise ValueError(f"data does not hold {self.height}x{self.width}x{self.channels} {self.sample} samples")
        array = np.frombuffer(raw, dtype).reshape(self.height, self.width, self.channels)
        if dtype.kind == "f" and not np.isfinite(array).all():
            raise ValueError("data holds a sample that is not finite")
        self._array = array
        return self

    @classmethod
    def of(cls, array: np.ndarray) -> Pixels:
        """The inline form of an (height, width, channels) array of a `SampleType`."""
        array = np.ascontiguousarray(array, np.dtype(array.dtype).newbyteorder("<"))
        data = base64.b64encode(zlib.compress(array.tobytes(), 1)).decode("ascii")
        height, width, channels = array.shape
        return cls(width=width, height=height, channels=channels, sample=str(array.dtype), data=data)

    @property
    def array(self) -> np.ndarray:
        """The samples as stored, (height, width, channels)."""
        return self._array

    def linear(self, raw: bool = False) -> np.ndarray:
        """Linear float32 values, (height, width, channels) (linear_values)."""
        return linear_values(self._array, raw)


def linear_values(samples: np.ndarray, raw: bool = False) -> np.ndarray:
    """Linear float32 values of samples of a `SampleType`: integer samples scaled to [0, 1]
    and, unless `raw`, decoded from sRGB (IEC 61966-2-1); float samples as they are."""
    if samples.dtype.kind == "f":
        return samples.astype(np.float32)
    v = samples.astype(np.float32) / np.float32(np.iinfo(samples.dtype).max)
    if raw:
        return v
    return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4).astype(np.float32)


def image_shape(path: Path) -> tuple[int, int, int]:
    """(height, width, channels) an image file declares, read from its header only."""
    image = oiio.ImageInput.open(str(path))
    if image is None:
        raise ImageError(_oiio_message(path))
    try:
        spec = image.spec()
        return spec.height, spec.width, spec.nchannels
    finally:
        image.close()


def read_image(path: Path) -> np.ndarray:
    """An image file's first subimage as (height, width, channels) samples of its own type
    (other integer types read as uint16, other float types as float32)."""
    image = oiio.ImageInput.open(str(path))
    if image is None:
        raise ImageError(_oiio_message(path))
    try:
        spec = image.spec()
        if not (1 <= spec.nchannels <= 4):
            raise ImageError(f"{spec.nchannels} channels (1 to 4 are read)")
        if max(spec.width, spec.height) > MAX_IMAGE_SIDE:
            raise ImageError(f"{spec.width}x{spec.height} pixels: a side is over {MAX_IMAGE_SIDE}")
        base = str(spec.format)
        sample = _OIIO_TYPES.get(base, "float32" if base == "double" else "uint16")
        oiio_type = {"uint8": "uint8", "uint16": "uint16", "float16": "half", "float32": "float"}[sample]
        pixels = image.read_image(0, 0, 0, spec.nchannels, oiio_type)
        if pixels is None:
            raise ImageError(_oiio_message(path, image))
    finally:
        image.close()
    array = np.asarray(pixels).reshape(spec.height, spec.width, spec.nchannels).astype(sample, copy=False)
    if array.dtype.kind == "f" and not np.isfinite(array).all():
        raise ImageError("holds a sample that is not finite")
    return array


def _oiio_message(path: Path, image: oiio.ImageInput | None = None) -> str:
    """OpenImageIO's error as one line, without the file's full path."""
    text = (image.geterror() if image is not None else oiio.geterror()) or "not an image OpenImageIO reads"
    return " ".join(text.replace(str(path), path.name).split())
