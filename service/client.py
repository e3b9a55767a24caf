"""`photonfarm submit`: a client of the HTTP API. Submits a bundled scene (by name) or a
scene file, and with --watch follows the job with a progress bar and writes the final image."""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

import httpx

from worker.store.policy import FINAL



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


def _body(args: argparse.Namespace) -> dict[str, Any]:
    settings: dict[str, Any] = {k: v for k, v in (
        ("error_threshold", args.threshold), ("max_seconds", args.max_seconds), ("max_passes", args.max_passes),
        ("photons_per_pass", args.photons_per_pass), ("confidence", args.confidence)) if v is not None}
    if args.resolution:
        settings["resolution"] = list(args.resolution)
    if args.scene.endswith(".json"):
        try:
            return {"scene": json.loads(Path(args.scene).read_text()), "settings": settings}
        except (OSError, json.JSONDecodeError) as exc:
            raise ClientError(f"cannot read scene file {args.scene}: {exc}") from None
    return {"scene_name": args.scene, "settings": settings}


def _progress(job: dict[str, Any], threshold: float | None) -> str:
    est = job.get("error_estimate") or {}
    error = f"error {est['error']:.4f}" if est else "error -"
    if threshold:
        frac = min(1.0, threshold / est["error"]) if est else 0.0
        error += f" -> {threshold}"
    else:
        budget = job["settings"].get("max_passes")
        frac = job["passes"] / budget if budget else min(1.0, job["elapsed_seconds"] / (job["settings"]["max_seconds"] or 1))
    bar = "#" * int(30 * frac)
    return (f"\r[{bar:<30}] {job['status']:<16} {job['passes']} passes  "
            f"{job['photons_per_second'] / 1e6:6.2f} M photons/s  {error}  {job['elapsed_seconds']:7.1f} s")


def submit(args: argparse.Namespace) -> int:
    client = Client(args.url, args.token)
    job = client.call("POST", "/v1/jobs", json=_body(args)).json()
    print(f"job {job['id']} {job['status']}: {args.url.rstrip('/')}{job['links']['self']}")
    if not args.watch:
        return 0
    while job["status"] not in FINAL:
        time.sleep(args.poll)
        job = client.call("GET", job["links"]["self"]).json()
        sys.stderr.write(_progress(job, args.threshold))
        sys.stderr.flush()
    sys.stderr.write("\n")
    if job["status"] == "failed":
        raise ClientError(f"job failed: {job['failure']}")
    out = args.out or Path(f"{Path(args.scene).stem}-{job['id']}.png")
    link = job["links"]["image_exr" if out.suffix.lower() == ".exr" else "image_png"]
    out.write_bytes(client.call("GET", link).content)
    print(f"{job['status']}: {job['passes']} passes, {job['photons']} photons, {job['elapsed_seconds']:.1f} s; "
          f"wrote {out}")
    return 0


def add_parser(sub: argparse._SubParsersAction, positive_float: Any, positive_int: Any, resolution: Any) -> None:
    p = sub.add_parser("submit", help="submit a job to a running service (HTTP)")
    p.add_argument("scene", help="bundled scene name, or a scene .json file sent inline")
    p.add_argument("--url", default=os.environ.get("PHOTONFARM_URL", "http://127.0.0.1:8000"))
    p.add_argument("--token", default=os.environ.get("PHOTONFARM_TOKEN") or None)
    p.add_argument("--threshold", type=positive_float, help="stop when the average relative error is this low")
    p.add_argument("--confidence", type=positive_float)
    p.add_argument("--max-seconds", type=positive_float)
    p.add_argument("--max-passes", type=positive_int)
    p.add_argument("--photons-per-pass", type=positive_int)
    p.add_argument("--resolution", type=resolution)
    p.add_argument("--watch", action="store_true", help="follow the job and write its final image")
    p.add_argument("--poll", type=positive_float, default=1.0, help="seconds between polls (default 1)")
    p.add_argument("--out", type=Path, help="final image, .png or .exr (default SCENE-ID.png)")
