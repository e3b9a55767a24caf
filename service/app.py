"""The HTTP API (FastAPI). OpenAPI at /docs.

It stores jobs and reads their state; it never renders. Batches run on the workers, and
this process only kicks a new job off and runs the reaper that re-issues lost batches.
"""

from __future__ import annotations

import datetime as dt
import json
import logging
import os
import tempfile
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any, AsyncIterator, Literal

import numpy as np
import redis
from fastapi import FastAPI, HTTPException, Query, Request, Response
from fastapi.exceptions import RequestValidationError
from fastapi.responses import FileResponse, JSONResponse
from fastapi.staticfiles import StaticFiles
from prometheus_client import CONTENT_TYPE_LATEST

from service.metrics import metrics_text, workers
from service.models import (MAX_ACTIVE_JOBS, MAX_BODY_BYTES, MAX_SERVICE_PIXELS, JobLinks, JobRequest, JobView,
                            SceneSummary)
from worker.image_io import error_colours, write_image
from worker.scene import SCENES_DIR, SceneError, bundled_scene_path, inline_meshes, load_scene_file, parse_scene
from worker.scheduler import Reaper, feed
from worker.settings import Settings
from worker.store import JobRecord, Jobs
from worker.store.policy import FINAL
from worker.store.record import JobLimitReached

log = logging.getLogger("photonfarm.api")
STATIC_DIR = Path(__file__).resolve().parent / "static"


def _iso(ts: float | None) -> str | None:
    return dt.datetime.fromtimestamp(ts, dt.timezone.utc).isoformat() if ts else None


def _unprocessable(loc: list[str | int], msg: str) -> HTTPException:
    return HTTPException(422, detail=[{"loc": loc, "msg": msg, "type": "value_error"}])


def job_view(jobs: Jobs, record: JobRecord, history: bool = False) -> JobView:
    base = f"/v1/jobs/{record.id}"
    return JobView(
        id=record.id, status=record.status, scene_name=record.scene_name, settings=record.settings,
        width=record.width, height=record.height, passes=record.passes, photons=record.emitted,
        elapsed_seconds=round(record.elapsed_seconds(), 3), photons_per_second=round(record.photons_per_second, 1),
        workers_active=jobs.leases.owners(record.id), created=_iso(record.created), started=_iso(record.started),
        finished=_iso(record.finished), failure=record.failure, error_estimate=jobs.last_error(record.id),
        error_history=jobs.history(record.id) if history else None,
        links=JobLinks(self=base, image_png=f"{base}/image?format=png", image_exr=f"{base}/image?format=exr",
                       error_png=f"{base}/error?format=png", error_exr=f"{base}/error?format=exr"))


def encode_image(pixels: np.ndarray, fmt: Literal["png", "exr"], **options: Any) -> bytes:
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / f"image.{fmt}"
        write_image(path, pixels, **options)
        return path.read_bytes()


MEDIA = {"png": "image/png", "exr": "image/x-exr"}


def create_app(redis_url: str, token: str | None = None, reaper: bool = True) -> FastAPI:
    conn = redis.Redis.from_url(redis_url, health_check_interval=10)
    jobs = Jobs(conn)

    @asynccontextmanager
    async def lifespan(_: FastAPI) -> AsyncIterator[None]:
        running = Reaper(jobs).start() if reaper else None
        yield
        if running is not None:
            running.stop()

    app = FastAPI(title="photonfarm", version="0.1.0", lifespan=lifespan,
                  description="Distributed progressive photon mapping (SPPM) render service.")

    @app.middleware("http")
    async def guard(request: Request, call_next):  # type: ignore[no-untyped-def]
        # The page and its script carry no data; every data route wants the token.
        open_path = request.url.path in ("/healthz", "/") or request.url.path.startswith("/static/")
        if token and not open_path and request.headers.get("authorization") != f"Bearer {token}":
            return JSONResponse({"detail": "missing or wrong bearer token"}, 401, headers={"WWW-Authenticate": "Bearer"})
        length = request.headers.get("content-length")
        if length is not None and length.isdigit() and int(length) > MAX_BODY_BYTES:
            return JSONResponse({"detail": f"body larger than {MAX_BODY_BYTES} bytes"}, 413)
        if length is None and request.method in ("POST", "PUT", "PATCH"):
            body = b""
            async for chunk in request.stream():
                body += chunk
                if len(body) > MAX_BODY_BYTES:
                    return JSONResponse({"detail": f"body larger than {MAX_BODY_BYTES} bytes"}, 413)
            request._body = body  # noqa: SLF001 - the stream is consumed; hand the body on
        try:
            return await call_next(request)
        except redis.ConnectionError:
            return JSONResponse({"detail": "job store unavailable, retry shortly"}, 503)

    @app.exception_handler(RequestValidationError)
    async def validation(_: Request, exc: RequestValidationError) -> JSONResponse:
        errors = [{"loc": list(e["loc"]), "msg": e["msg"], "type": e["type"]} for e in exc.errors()]
        return JSONResponse({"detail": errors}, 422)

    def existing(job_id: str) -> JobRecord:
        record = jobs.get(job_id)
        if record is None:
            raise HTTPException(404, detail=f"no job {job_id!r}")
        return record

    app.mount("/static", StaticFiles(directory=STATIC_DIR), name="static")

    @app.get("/", include_in_schema=False)
    def page() -> FileResponse:
        """The web viewer: submit, follow, watch the image refine, cancel, download."""
        return FileResponse(STATIC_DIR / "index.html")

    @app.get("/healthz")
    def healthz() -> dict[str, Any]:
        try:
            ok = bool(conn.ping())
        except redis.RedisError:
            ok = False
        if not ok:
            raise HTTPException(503, detail="redis unreachable")
        return {"status": "ok"}

    @app.get("/metrics", response_class=Response)
    def metrics() -> Response:
        """Prometheus text format: jobs by status, batches merged, photons per second, merge
        latency, queue depth, workers alive."""
        return Response(metrics_text(jobs), media_type=CONTENT_TYPE_LATEST)

    @app.get("/v1/workers")
    def list_workers() -> list[dict[str, Any]]:
        """Every registered worker: host, pid, state, last heartbeat, current job and batch."""
        return workers(jobs)

    @app.get("/v1/scenes", response_model=list[SceneSummary])
    def scenes() -> list[SceneSummary]:
        out = []
        for path in sorted(SCENES_DIR.glob("*.json")):
            out.append(SceneSummary(name=path.stem, description=json.loads(path.read_text()).get("description", "")))
        return out

    @app.get("/v1/scenes/{name}")
    def scene(name: str) -> dict[str, Any]:
        try:
            return json.loads(bundled_scene_path(name).read_text())
        except SceneError as exc:
            raise HTTPException(404, detail=exc.message) from None

    @app.post("/v1/jobs", status_code=201, response_model=JobView)
    def submit(body: JobRequest, response: Response) -> JobView:
        try:
            if body.scene_name is not None:
                parsed, base_dir = load_scene_file(bundled_scene_path(body.scene_name))
            else:
                parsed, base_dir = parse_scene(body.scene), SCENES_DIR
            scene_json = inline_meshes(parsed, base_dir)
        except SceneError as exc:
            if body.scene_name is not None:
                raise _unprocessable(["body", "scene_name"], exc.message) from None
            loc = ["body", "scene", *[int(p) if p.isdigit() else p for p in exc.field.split(".") if p]]
            raise _unprocessable(loc, exc.message) from None
        settings = body.settings
        width, height = settings.resolution or parsed.camera.resolution
        if width * height > MAX_SERVICE_PIXELS:
            raise _unprocessable(["body", "scene", "camera", "resolution"],
                                 f"at most {MAX_SERVICE_PIXELS} pixels per job")
        try:
            job_id = jobs.create(scene_json, Settings(**dict(settings)), width, height, body.scene_name,
                                 max_active=MAX_ACTIVE_JOBS)
        except JobLimitReached as exc:
            raise _unprocessable(["body"], str(exc)) from None
        feed(jobs, job_id)
        response.headers["Location"] = f"/v1/jobs/{job_id}"
        log.info(f"job submitted: {body.scene_name or 'inline scene'} {width}x{height}", extra={"job": job_id})
        return job_view(jobs, jobs.get(job_id))

    @app.get("/v1/jobs", response_model=list[JobView])
    def list_jobs(response: Response, offset: int = Query(0, ge=0),
                  limit: int = Query(50, ge=1, le=500)) -> list[JobView]:
        """Jobs, newest first, a page at a time; X-Total-Count says how many there are."""
        records = (jobs.get(job_id) for job_id in jobs.ids(offset, limit, newest_first=True))
        response.headers["X-Total-Count"] = str(jobs.count())
        return [job_view(jobs, record) for record in records if record is not None]

    @app.get("/v1/jobs/{job_id}", response_model=JobView)
    def job(job_id: str) -> JobView:
        return job_view(jobs, existing(job_id), history=True)

    @app.delete("/v1/jobs/{job_id}", response_model=JobView, status_code=202,
                responses={204: {"description": "the finished job and its images were deleted"}})
    def cancel_or_delete(job_id: str) -> Response | JobView:
        """An active job is cancelled (202: it stops within a pass and keeps its image); a
        finished one is deleted with its state and images (204)."""
        record = existing(job_id)
        if record.status in FINAL:
            jobs.delete(job_id)
            return Response(status_code=204)
        jobs.cancel(job_id)
        return job_view(jobs, jobs.get(job_id))

    @app.get("/v1/jobs/{job_id}/image", responses={200: {"content": {"image/png": {}, "image/x-exr": {}}}})
    def image(job_id: str, format: Literal["png", "exr"] = Query("png")) -> Response:  # noqa: A002
        record = existing(job_id)
        w, h = record.width, record.height
        state = jobs.state(record)
        rgb = record.integrator.image(state).reshape(h, w, 3) if state is not None else np.zeros((h, w, 3))
        return Response(encode_image(rgb, format), media_type=MEDIA[format],
                        headers={"X-Passes": str(record.passes), "X-Photons": str(record.emitted)})

    @app.get("/v1/jobs/{job_id}/error", responses={200: {"content": {"image/png": {}, "image/x-exr": {}}}})
    def error_map(job_id: str, format: Literal["png", "exr"] = Query("png")) -> Response:  # noqa: A002
        """PNG: relative error, colour-coded on a log scale (blue 0.1%, green 1%, yellow 10%,
        red 100%). EXR: the bias, noise and bound channels (luminance) and the relative error."""
        record = existing(job_id)
        w, h = record.width, record.height
        state = jobs.state(record)
        if state is None:
            raise HTTPException(409, detail="no pass merged yet")
        est = record.integrator.estimate(state)
        if est is None:
            raise HTTPException(409, detail="this job does not estimate its error (error_estimation is off)")
        if format == "png":
            body = encode_image(error_colours(est.relative, est.measured).reshape(h, w, 3), "png", display=True)
        else:
            channels = np.stack([est.bias, est.noise, est.bound, est.relative], axis=-1).reshape(h, w, 4)
            body = encode_image(channels, "exr", channels=("bias", "noise", "bound", "relative"))
        return Response(body, media_type=MEDIA[format], headers={"X-Passes": str(record.passes),
                                                                 "X-Average-Relative-Error": f"{est.average:.6g}"})

    return app


def app_from_env() -> FastAPI:
    """For `uvicorn service.app:app_from_env --factory`: REDIS_URL and PHOTONFARM_TOKEN."""
    return create_app(os.environ["REDIS_URL"], os.environ.get("PHOTONFARM_TOKEN") or None)
