"""`photonfarm submit`: a client of the HTTP API. Submits a bundled scene (by name) or a
scene file, and with --watch follows the job with a progress bar and writes the final image."""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

import httpx
import numpy as np
from tqdm import tqdm

from service.models import MAX_BODY_BYTES
from service.upload import MAX_UPLOAD_FILES
from worker.config import config
from worker.images import IMAGE_SUFFIXES
from worker.outputs import check_writable
from worker.scene import SceneError, scene_file
from worker.store.policy import FINAL

UPLOAD_SUFFIXES = (".json", ".xml", ".obj", ".ply", ".serialized", ".spd", *IMAGE_SUFFIXES)  # what a scene may name


class ClientError(Exception):
    """Something the user can fix, said in one line."""


def _detail(resp: httpx.Response) -> str:
    try:
        detail = resp.json()["detail"]
    except (ValueError, KeyError):
        return resp.text[:300]
    if isinstance(detail, list):
        return "; ".join(f"{'.'.join(str(p) for p in d['loc'] if p != 'body')}: {d['msg']}" for d in detail)
    return str(detail)


class Client:
    def __init__(self, url: str, token: str | None) -> None:
        headers = {"Authorization": f"Bearer {token}"} if token else {}
        self.http = httpx.Client(base_url=url.rstrip("/"), headers=headers, timeout=60)

    def call(self, method: str, path: str, **kwargs: Any) -> httpx.Response:
        try:
            resp = self.http.request(method, path, **kwargs)
        except httpx.TransportError as exc:
            raise ClientError(f"cannot reach {self.http.base_url}: {exc}") from None
        if resp.status_code >= 400:
            raise ClientError(f"HTTP {resp.status_code}: {_detail(resp)}")
        return resp


def _settings(args: argparse.Namespace) -> dict[str, Any]:
    settings: dict[str, Any] = {k: v for k, v in (
        ("error_threshold", args.threshold), ("max_seconds", args.max_seconds), ("max_passes", args.max_passes),
        ("photons_per_pass", args.photons_per_pass), ("confidence", args.confidence)) if v is not None}
    if args.resolution:
        settings["resolution"] = list(args.resolution)
    return settings


def _names_files(scene: dict[str, Any]) -> bool:
    textures = scene.get("textures")
    parts = [*(scene.get("shapes") or []), *(textures.values() if isinstance(textures, dict) else [])]
    return any(isinstance(part, dict) and "file" in part for part in parts)


def scene_folder_files(scene_file: Path) -> list[tuple[str, Path]]:
    """The files sent with a scene file: every scene, mesh, spectrum or image file (UPLOAD_SUFFIXES) in
    its folder and below, by path relative to it, within the service's upload limits. The
    service reads only what the scene names, and only inside this upload."""
    folder = scene_file.resolve().parent
    found: list[Path] = []
    size = 0
    for path in folder.rglob("*"):  # stops at the limits, so a large folder is not walked through
        if path.suffix.lower() not in UPLOAD_SUFFIXES or not path.is_file() \
                or any(part.startswith(".") for part in path.relative_to(folder).parts):
            continue
        found.append(path)
        size += path.stat().st_size
        if len(found) > MAX_UPLOAD_FILES or size > MAX_BODY_BYTES:
            raise ClientError(f"{folder} holds more scene and mesh files than one upload takes ({MAX_UPLOAD_FILES} "
                              f"files, {MAX_BODY_BYTES} bytes): put the scene in a folder of its own")
    return [(path.relative_to(folder).as_posix(), path) for path in sorted(found)]


def _post_job(client: Client, args: argparse.Namespace) -> dict[str, Any]:
    """A bundled scene or a plain JSON scene go as JSON; a scene that names files (meshes,
    includes) and any Mitsuba .xml go as an upload with the files beside them."""
    settings = _settings(args)
    try:
        path = scene_file(args.scene)
    except SceneError as exc:
        raise ClientError(exc.message) from None
    if path is None:
        return client.call("POST", "/v1/jobs", json={"scene_name": args.scene, "settings": settings}).json()
    try:
        scene = json.loads(path.read_text()) if path.suffix.lower() == ".json" else None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ClientError(f"cannot read scene file {args.scene}: {exc}") from None
    if isinstance(scene, dict) and not _names_files(scene):
        return client.call("POST", "/v1/jobs", json={"scene": scene, "settings": settings}).json()
    if not path.is_file():
        raise ClientError(f"scene file {args.scene} not found")
    files = scene_folder_files(path)
    with contextlib.ExitStack() as stack:
        parts = [("files", (name, stack.enter_context(local.open("rb")))) for name, local in files]
        return client.call("POST", "/v1/jobs/upload", files=parts,
                           data={"scene": path.name, "settings": json.dumps(settings)}).json()


def eta_seconds(job: dict[str, Any]) -> float | None:
    """Seconds left: from the error's slope when the job has a threshold (a power law fitted
    to its error history, log error against log seconds), else from its budget."""
    settings = job["settings"]
    threshold = settings.get("error_threshold")
    history = [h for h in job.get("error_history") or [] if h.get("error") and h["seconds"] > 0]
    if threshold and len(history) >= 3:
        recent = history[len(history) // 2:]
        t = np.log([h["seconds"] for h in recent])
        e = np.log([h["error"] for h in recent])
        slope = float(np.polyfit(t, e, 1)[0]) if np.ptp(t) > 0 else 0.0
        if slope < 0:  # seconds at which the fitted error meets the threshold
            return max(0.0, float(np.exp(t[-1] + (np.log(threshold) - e[-1]) / slope)) - job["elapsed_seconds"])
    if settings.get("max_seconds"):
        return max(0.0, settings["max_seconds"] - job["elapsed_seconds"])
    if settings.get("max_passes") and job["passes"] > 0:
        return job["elapsed_seconds"] * (settings["max_passes"] - job["passes"]) / job["passes"]
    return None


def _watch(client: Client, job: dict[str, Any], poll: float) -> dict[str, Any]:
    """Follow a job to its end with a progress bar (tqdm; none when stderr is not a terminal)."""
    with tqdm(total=1.0, file=sys.stderr, disable=None, bar_format="{l_bar}{bar}| {postfix}") as bar:
        while job["status"] not in FINAL:
            time.sleep(poll)
            job = client.call("GET", job["links"]["self"]).json()
            eta = eta_seconds(job)
            done = job["elapsed_seconds"] / (job["elapsed_seconds"] + eta) if eta is not None else 0.0
            est = job.get("error_estimate") or {}
            bar.n = min(1.0, done)
            bar.set_postfix_str(f"{job['status']} {job['passes']} passes "
                                f"{job['photons_per_second'] / 1e6:.2f} M photons/s error "
                                f"{est.get('error') or float('nan'):.4f} "
                                f"ETA {eta if eta is not None else float('nan'):.0f} s",
                                refresh=True)
    return job


def submit(args: argparse.Namespace) -> int:
    client = Client(args.url, args.token)
    if args.watch:  # the image is written after the job's end: its place is checked first
        try:
            if args.out is not None:
                check_writable(args.out)
            elif not os.access(Path.cwd(), os.W_OK):
                raise ValueError(f"cannot write the image into {Path.cwd()}: give --out")
        except ValueError as exc:
            raise ClientError(str(exc)) from None
    job = _post_job(client, args)
    print(f"job {job['id']} {job['status']}: {args.url.rstrip('/')}{job['links']['self']}")
    for note in job.get("notes") or []:
        print(f"photonfarm: {note}", file=sys.stderr)
    if not args.watch:
        return 0
    job = _watch(client, job, args.poll)
    if job["status"] == "failed":
        raise ClientError(f"job failed: {job['failure']}")
    out = args.out or Path(f"{Path(args.scene).stem}-{job['id']}.png")
    link = job["links"]["image_exr" if out.suffix.lower() == ".exr" else "image_png"]
    try:
        out.write_bytes(client.call("GET", link).content)
    except OSError as exc:
        raise ClientError(f"cannot write {out}: {exc.strerror or exc}; the image stays at "
                          f"{args.url.rstrip('/')}{link}") from None
    print(f"{job['status']}: {job['passes']} passes, {job['photons']} photons, {job['elapsed_seconds']:.1f} s; "
          f"wrote {out}")
    return 0


def add_parser(sub: argparse._SubParsersAction, positive_float: Any, positive_int: Any, resolution: Any,
               output: Any) -> None:
    p = sub.add_parser("submit", help="submit a job to a running service (HTTP)")
    p.add_argument("scene", help="bundled scene name, or a scene .json or Mitsuba .xml file (sent with the scene "
                                 "and mesh files of its folder)")
    p.add_argument("--url", default=config().url, help=f"the API (default: $PHOTONFARM_URL, else {config().url})")
    p.add_argument("--token", default=config().token,
                   help="the API's bearer token (default: $PHOTONFARM_TOKEN or the file $PHOTONFARM_TOKEN_FILE "
                        "names; a token on the command line is readable by any local user)")
    p.add_argument("--threshold", type=positive_float, help="stop when the average relative error is this low")
    p.add_argument("--confidence", type=positive_float)
    p.add_argument("--max-seconds", type=positive_float)
    p.add_argument("--max-passes", type=positive_int)
    p.add_argument("--photons-per-pass", type=positive_int)
    p.add_argument("--resolution", type=resolution)
    p.add_argument("--watch", action="store_true", help="follow the job and write its final image")
    p.add_argument("--poll", type=positive_float, default=1.0, help="seconds between polls (default 1)")
    p.add_argument("--out", type=output, help="final image, .png or .exr (default SCENE-ID.png)")
