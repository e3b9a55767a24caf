"""Shared by the benchmarks: engines, output files, the smallppm peer's scene and the image
error metric.

The error metric compares images in smallppm's display space: v = (1 - exp(-x))^(1/2.2)
for linear radiance x (smallppm's own 8-bit output is read as v = byte / 255), then the
RMS of v_img - v_ref over all pixels and channels.
"""

from __future__ import annotations

import json
from pathlib import Path

import matplotlib
import numpy as np
import psutil

from worker.engine import Engine
from worker.scene import bundled_scene_path, load_scene_file
from worker.settings import Settings

matplotlib.use("Agg")  # charts are files

BENCH_DIR = Path(__file__).resolve().parent
OUT_DIR = BENCH_DIR / "out"
PEERS_FILE = BENCH_DIR / "peers.json"
REFERENCE_FILE = BENCH_DIR / "reference" / "smallppm-ref.exr"

def display(rgb: np.ndarray) -> np.ndarray:
    """smallppm's tone curve without 8-bit quantisation: (1 - exp(-x))^(1/2.2)."""
    x = np.clip(np.nan_to_num(rgb, nan=0.0, posinf=1e30), 0.0, None)
    return (1.0 - np.exp(-x)) ** (1.0 / 2.2)


def display_rms(img: np.ndarray, ref_display: np.ndarray) -> float:
    """RMS over pixels and channels of display(img) - ref_display."""
    return float(np.sqrt(np.mean((display(img) - ref_display) ** 2)))


def box2x2(img: np.ndarray) -> np.ndarray:
    """Halve an (H, W, C) image by averaging 2x2 blocks (H and W even)."""
    h, w, c = img.shape
    return img.reshape(h // 2, 2, w // 2, 2, c).mean(axis=(1, 3))


def read_ppm(path: Path | str) -> np.ndarray:
    """A plain (P3) or binary (P6) PPM as (H, W, 3) float64 in [0, 1], top row first."""
    data = Path(path).read_bytes()
    if data[:2] == b"P6":
        parts = data.split(maxsplit=4)
        w, h, maxval = int(parts[1]), int(parts[2]), int(parts[3])
        pix = np.frombuffer(parts[4][: w * h * 3], np.uint8)
    else:
        tokens = data.split()
        w, h, maxval = int(tokens[1]), int(tokens[2]), int(tokens[3])
        pix = np.array(tokens[4 : 4 + w * h * 3], dtype=np.float64)
    return pix.reshape(h, w, 3).astype(np.float64) / maxval


def bench_engine(scene: str, resolution: tuple[int, int] | None = None, **settings: object) -> Engine:
    """An Engine for a bundled scene with the given settings fields (the rest default)."""
    parsed, base = load_scene_file(bundled_scene_path(scene))
    return Engine(parsed, base, Settings(resolution=resolution, **settings))


def cpu_seconds(pids: list[int]) -> float:
    """User and system CPU seconds of these processes so far, with their children that
    ended (e.g. redis-server's append-only-file rewrite, a forked child)."""
    total = 0.0
    for pid in pids:
        t = psutil.Process(pid).cpu_times()
        total += t.user + t.system + t.children_user + t.children_system
    return total


def core_times() -> list:
    """Each core's times so far (psutil: user, system, idle, steal, ...)."""
    return psutil.cpu_times(percpu=True)


def host_seconds(before: list, after: list, ours: float) -> dict[str, object]:
    """What the cores did between two core_times(): per core, the seconds the hypervisor
    gave to other guests (steal: this VM wanted the core and did not get it) and the busy
    seconds; and the busy seconds of processes other than ours (`ours`: their CPU seconds
    over the same span)."""
    steal = [a.steal - b.steal for b, a in zip(before, after, strict=True)]
    busy = [(a.user + a.nice + a.system + a.irq + a.softirq) - (b.user + b.nice + b.system + b.irq + b.softirq)
            for b, a in zip(before, after, strict=True)]
    return {"steal_seconds": steal, "busy_seconds": busy, "others_cpu_seconds": sum(busy) - ours}


def write_json(name: str, report: object) -> Path:
    """bench/out/NAME.json."""
    OUT_DIR.mkdir(parents=True, exist_ok=True)
    path = OUT_DIR / f"{name}.json"
    path.write_text(json.dumps(report, indent=1) + "\n")
    return path


def save_figure(fig: object, name: str) -> Path:
    """bench/out/NAME.png (a matplotlib figure), then closes it."""
    import matplotlib.pyplot as plt

    OUT_DIR.mkdir(parents=True, exist_ok=True)
    path = OUT_DIR / f"{name}.png"
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path
