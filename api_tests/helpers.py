"""Helpers the API test modules share: the exact-totals check of a finished job, image
bytes as served decoded, scene archives built in memory, and the headless Chromium."""

from __future__ import annotations

import io
import shutil
import tempfile
import zipfile
from pathlib import Path

import numpy as np

from api_tests.cluster import Cluster, finished, merged_passes
from service.upload import MAX_UPLOAD_BYTES
from worker.image_io import read_image

CHROMIUM = shutil.which("chromium")  # Debian's chromium; Playwright downloads no browser
CHROMIUM_FLAGS = ["--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                  "--disable-background-networking", "--disable-component-update", "--disable-sync"]


def assert_exact(c: Cluster, job_id: str, passes: int, photons_per_pass: int, timeout: float = 120.0) -> dict:
    """The job completes with exactly `passes` passes of `photons_per_pass` photons, its
    merged batches tiling 0..passes-1 (every pass merged once, none lost); returns the job."""
    done = c.wait(job_id, finished, timeout=timeout)
    assert done["status"] == "completed", done
    assert done["passes"] == passes and done["photons"] == passes * photons_per_pass, done
    assert merged_passes(c.redis_client, job_id) == list(range(passes))
    return done


def decode_image(data: bytes, suffix: str) -> np.ndarray:
    """An image file's bytes (`suffix` ".exr" or ".png" says the format) as an array."""
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / f"x{suffix}"
        path.write_bytes(data)
        return read_image(path)


def zip_bytes(entries: dict[str, bytes]) -> bytes:
    """A deflated zip archive of `entries` (member name: contents)."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as z:
        for name, data in entries.items():
            z.writestr(name, data)
    return buf.getvalue()


def zip_bomb() -> bytes:
    """A small zip (about 130 KB) of one member of zeros that unpacks past the upload limit."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED, compresslevel=9) as z:
        with z.open("zeros.ply", "w", force_zip64=True) as out:
            block = bytes(1 << 20)
            for _ in range(MAX_UPLOAD_BYTES // len(block) + 1):
                out.write(block)
    return buf.getvalue()
