"""The HTTP API (FastAPI). OpenAPI at /docs.

It stores jobs and serves the images their reducers publish (worker/reducer.py); it never
renders nor folds, and holds no job state: any number of API processes may serve one farm.
Batches run on the workers; this process only kicks a new job off.
"""

from __future__ import annotations

import datetime as dt
import hmac
import json
import logging
import math
import sys
import tempfile
import threading
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Annotated, Any, Literal

import cachetools
import numpy as np
import redis
from fastapi import FastAPI, File, Form, HTTPException, Query, Request, Response, Security, UploadFile
from fastapi import Path as PathParam
from fastapi.exception_handlers import http_exception_handler
from fastapi.exceptions import RequestValidationError
from fastapi.responses import FileResponse, JSONResponse
from fastapi.security import HTTPBearer
from fastapi.staticfiles import StaticFiles
from fastapi_offline import FastAPIOffline
from prometheus_client import CONTENT_TYPE_LATEST
from pydantic import ValidationError
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.routing import Mount, Route

from service.metrics import metrics_text, workers
from service.models import (
    MAX_ACTIVE_JOBS,
    MAX_BODY_BYTES,
    MAX_SERVICE_PIXELS,
    ErrorBody,
    JobLinks,
    JobRequest,
    JobSettings,
    JobView,
    PixelView,
    SceneSummary,
)
from service.scene_loader import LoadedScene, LoadUnavailable, SceneLoader, SceneRequest
from service.upload import Unpacker, UploadError, scene_path
from worker.config import ConfigError, config
from worker.image_io import error_colours, write_image
from worker.outputs import write_render
from worker.scene import (
    MAX_SCENE_NAME,
    SCENE_NAME_PATTERN,
    SceneError,
    SceneLimitError,
    bundled_scene_names,
    bundled_scene_path,
)
from worker.scheduler import feed
from worker.settings import Settings
from worker.store import JobRecord, Jobs
from worker.store.connection import connect
from worker.store.policy import FINAL
from worker.store.record import JobLimitReached

log = logging.getLogger("photonfarm.api")
# Repeated reads come from memory, so pollers do not take CPU from the workers on a shared host:
ENCODED_CACHE_BYTES = 64 * 1024 * 1024  # encoded images and error maps, by (job, passes merged, format)
PIXEL_CACHE_JOBS = 2  # jobs whose per-pixel estimate and error are kept for GET .../pixel (cursor readouts)
MAX_LIST_OFFSET = 1 << 48  # GET /v1/jobs pages start below this (Redis takes 64-bit ranges; no farm holds more jobs)
METRICS_SECONDS = 1.0  # a /metrics scrape reads every job from Redis at most this often
STATIC_DIR = Path(__file__).resolve().parent / "static"
DOCS_ASSETS = "/docs/assets"  # Swagger UI and ReDoc files, served from the fastapi-offline package
# Paths without data, open without the token: the viewer page, the API description and its viewers.
OPEN_PATHS = ("/healthz", "/", "/openapi.json", "/docs", "/docs/oauth2-redirect", "/redoc")
OPEN_PREFIXES = ("/static/", f"{DOCS_ASSETS}/")
REASONS = {401: "missing or wrong bearer token (when PHOTONFARM_TOKEN is set)", 404: "no such job or scene",
           409: "not possible in the job's state", 413: f"body larger than {MAX_BODY_BYTES} bytes",
           422: "a bad field, named in detail[].loc", 429: "as many jobs active as the service allows; retry later",
           503: "the job store (Redis) is unavailable"}


def errors(*codes: int) -> dict[int | str, dict[str, Any]]:
    """OpenAPI `responses` for these error statuses, all with the ErrorBody shape."""
    return {code: {"model": ErrorBody, "description": REASONS[code]} for code in (*codes, 503)}


# An encoder of a job's image body: (record, format) to (body, headers).
Encoder = Callable[[JobRecord, Literal["png", "exr"]], tuple[bytes, dict[str, str]]]


def _iso(ts: float | None) -> str | None:
    return dt.datetime.fromtimestamp(ts, dt.UTC).isoformat() if ts else None


def _unprocessable(loc: list[str | int], msg: str) -> HTTPException:
    return HTTPException(422, detail=[{"loc": loc, "msg": msg, "type": "value_error"}])


def job_view(jobs: Jobs, record: JobRecord, history: bool = False) -> JobView:
    base = f"/v1/jobs/{record.id}"
    return JobView(
        id=record.id, status=record.status, scene_name=record.scene_name, settings=record.settings,
        width=record.width, height=record.height, passes=record.passes, image_passes=record.image_passes,
        photons=record.emitted,
        elapsed_seconds=round(record.elapsed_seconds(), 3), photons_per_second=round(record.photons_per_second, 1),
        workers_active=jobs.leases.owners(record.id), created=_iso(record.created), started=_iso(record.started),
        finished=_iso(record.finished), failure=record.failure, error_estimate=jobs.last_error(record.id),
        error_history=jobs.history(record.id) if history else None,
        notes=[*record.notes, *record.integrator.notes(record.counters)],
        links=JobLinks(self=base, image_png=f"{base}/image?format=png", image_exr=f"{base}/image?format=exr",
                       error_png=f"{base}/error?format=png", error_exr=f"{base}/error?format=exr"))


def encode_with(fmt: Literal["png", "exr"], write: Callable[[Path], None]) -> bytes:
    """The bytes `write` puts in a file of format `fmt` (OpenImageIO writes to files)."""
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / f"image.{fmt}"
        write(path)
        return path.read_bytes()


def encode_image(pixels: np.ndarray, fmt: Literal["png", "exr"], **options: Any) -> bytes:
    return encode_with(fmt, lambda path: write_image(path, pixels, **options))


MEDIA = {"png": "image/png", "exr": "image/x-exr"}
VALIDATOR_HEADERS = {"ETag": {"description": "strong validator of this image: send it back in If-None-Match",
                              "schema": {"type": "string"}},
                     "Cache-Control": {"description": "no-cache: revalidate before each reuse",
                                       "schema": {"type": "string"}}}
NOT_MODIFIED = {"description": "the image is the one If-None-Match names (no body)", "headers": VALIDATOR_HEADERS}


def etag(record: JobRecord, kind: str, fmt: str, passes: int) -> str:
    """A strong ETag: an image is a function of its job and the passes folded into it (the
    encoded cache's key), so one tag names one body."""
    return f'"{record.id}-{kind}-{fmt}-{passes}"'


def if_none_match(request: Request) -> set[str]:
    """The entity tags of If-None-Match, compared weakly as RFC 9110 (13.1.2) asks: W/ dropped."""
    tags = request.headers.get("if-none-match", "").split(",")
    return {tag.strip().removeprefix("W/") for tag in tags if tag.strip()}


def create_app(redis_url: str, token: str | None = None) -> FastAPI:
    conn = connect(redis_url)
    jobs = Jobs(conn)

    app = FastAPIOffline(title="photonfarm", version="0.1.0", static_url=DOCS_ASSETS,
                         description="Distributed progressive photon mapping (SPPM) render service.",
                         swagger_ui_parameters={"validatorUrl": None})  # no badge fetched from a public host
    bearer = HTTPBearer(auto_error=False, description="the server's PHOTONFARM_TOKEN")
    # Declared on every data route when a token is set (the Authorize button of /docs);
    # enforced by the guard below, before a body is read.
    secured = [Security(bearer)] if token else []
    auth = (401,) if token else ()

    def token_matches(presented: str, expected: str) -> bool:
        return hmac.compare_digest(presented.encode(), expected.encode())  # constant time

    @app.middleware("http")
    async def guard(request: Request, call_next: Callable[[Request], Awaitable[Response]]) -> Response:
        # The page, its script and the API description carry no data; every data route wants the token.
        path = request.url.path
        open_path = path in OPEN_PATHS or path.startswith(OPEN_PREFIXES)
        if token and not open_path:
            credentials = await bearer(request)  # the scheme compares case-insensitively (RFC 7235)
            if credentials is None or not token_matches(credentials.credentials, token):
                return JSONResponse({"detail": "missing or wrong bearer token"}, 401,
                                    headers={"WWW-Authenticate": "Bearer"})
        length = request.headers.get("content-length")
        if length is not None and length.isdigit() and int(length) > MAX_BODY_BYTES:
            return JSONResponse({"detail": f"body larger than {MAX_BODY_BYTES} bytes"}, 413)
        if length is None and request.method in ("POST", "PUT", "PATCH"):
            body = b""
            async for chunk in request.stream():
                body += chunk
                if len(body) > MAX_BODY_BYTES:
                    return JSONResponse({"detail": f"body larger than {MAX_BODY_BYTES} bytes"}, 413)
            request._body = body  # the stream is consumed: the route reads the body from here
        try:
            return await call_next(request)
        except (redis.ConnectionError, redis.TimeoutError):
            return JSONResponse({"detail": "job store unavailable, retry shortly"}, 503)
        except redis.exceptions.OutOfMemoryError:  # the memory cap (maxmemory, no eviction)
            return JSONResponse({"detail": "job store full: delete finished jobs or raise its memory cap"}, 507)

    @app.exception_handler(RequestValidationError)
    async def validation(_: Request, exc: RequestValidationError) -> JSONResponse:
        found = [{"loc": list(e["loc"]), "msg": e["msg"], "type": e["type"]} for e in exc.errors()]
        return JSONResponse({"detail": found}, 422)

    @app.exception_handler(StarletteHTTPException)
    async def http_error(request: Request, exc: StarletteHTTPException) -> Response:
        # FastAPI answers 400 for a body json.loads cannot take: undecodable bytes
        # (UnicodeDecodeError), an integer past Python's digit limit (ValueError), or nesting
        # past the parser's recursion limit (RecursionError);
        # Starlette for a malformed multipart form (its reason in the detail).
        if exc.status_code == 400:
            if isinstance(exc.__cause__, RecursionError):
                reason, kind = "body is nested too deeply", "json_invalid"
            elif isinstance(exc.__cause__, ValueError) and "integer string conversion" in str(exc.__cause__):
                reason = f"body holds an integer with more than {sys.get_int_max_str_digits()} digits"
                kind = "json_invalid"
            elif isinstance(exc.__cause__, ValueError):
                reason, kind = "body is not UTF-8 JSON", "json_invalid"
            else:
                reason, kind = f"body is not a readable form: {exc.detail}", "form_invalid"
            return JSONResponse({"detail": [{"loc": ["body"], "msg": reason, "type": kind}]}, 422)
        if exc.status_code == 405 and (allowed := allowed_methods(request.url.path)):
            # Starlette names the first route of the path only (RFC 9110, 15.5.6: every method)
            exc.headers = {**(exc.headers or {}), "Allow": ", ".join(sorted(allowed))}
        return await http_exception_handler(request, exc)

    def allowed_methods(path: str) -> set[str]:
        """Every method of the path template that takes `path` (the first that matches, as
        the router picks it; /v1/jobs/upload is not a job id): its operations in the schema."""
        for route in app.routes:
            if isinstance(route, Route) and route.path_regex.match(path):
                return {method for other in app.routes if isinstance(other, Route) and other.path == route.path
                        for method in other.methods or ()}
            if isinstance(route, Mount) and isinstance(route.app, StaticFiles) and route.path_regex.match(path):
                return {"GET", "HEAD"}  # what StaticFiles serves
        return set()

    # Encoded bodies keyed by the passes folded into the image: a new fold makes a new key, so
    # nothing stale is served; concurrent misses of one key wait for a single encode (the condition).
    encoded: cachetools.LRUCache[tuple[str, str, int, str], tuple[bytes, dict[str, str]]] = cachetools.LRUCache(
        maxsize=ENCODED_CACHE_BYTES, getsizeof=lambda value: len(value[0]))
    encoding = threading.Condition()

    def by_passes(kind: str) -> Callable[[Encoder], Encoder]:
        return cachetools.cached(encoded, key=lambda record, fmt: (kind, record.id, record.image_passes, fmt),
                                 condition=encoding)

    @by_passes("image")
    def image_body(record: JobRecord, fmt: Literal["png", "exr"]) -> tuple[bytes, dict[str, str]]:
        w, h = record.width, record.height
        published = jobs.published(record)
        if published is None:
            return encode_image(np.zeros((h, w, 3)), fmt), {"X-Passes": "0", "X-Photons": "0"}
        headers = {"X-Passes": str(published.passes), "X-Photons": str(published.emitted)}  # as folded
        # EXR: with the render's metadata (passes, photons, seed, settings, error estimate)
        return encode_with(fmt, lambda path: write_render(path, record.settings, published, w, h,
                                                          error_layers=False)), headers

    @by_passes("error")
    def error_body(record: JobRecord, fmt: Literal["png", "exr"]) -> tuple[bytes, dict[str, str]]:
        w, h = record.width, record.height
        published = jobs.published(record)
        if published is None:
            raise HTTPException(409, detail="no pass merged yet")
        est = published.estimate
        if est is None:
            raise HTTPException(409, detail="this job does not estimate its error (error_estimation is off)")
        if fmt == "png":
            body = encode_image(error_colours(est.relative, est.measured).reshape(h, w, 3), "png", display=True)
        else:
            channels = np.stack([est.bias, est.noise, est.bound, est.relative], axis=-1).reshape(h, w, 4)
            body = encode_image(channels, "exr", channels=("bias", "noise", "bound", "relative"))
        return body, {"X-Passes": str(published.passes), "X-Average-Relative-Error": f"{est.average:.6g}"}

    @cachetools.cached(cachetools.LRUCache(maxsize=PIXEL_CACHE_JOBS),
                       key=lambda record: (record.id, record.image_passes), condition=threading.Condition())
    def pixel_arrays(record: JobRecord) -> dict[str, np.ndarray] | None:
        """The estimate and its error per pixel, (h, w, ...) as the images, by passes merged."""
        published = jobs.published(record)
        if published is None:
            return None
        shape = (record.height, record.width)
        arrays = {"rgb": published.rgb.reshape(*shape, 3)}
        est = published.estimate
        if est is not None:
            arrays |= {name: getattr(est, name).reshape(shape)
                       for name in ("luminance", "bound", "relative", "measured")}
        return arrays

    @cachetools.cached(cachetools.TTLCache(maxsize=1, ttl=METRICS_SECONDS), key=lambda: "metrics",
                       condition=threading.Condition())
    def metrics_body() -> bytes:
        return metrics_text(jobs)

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

    @app.get("/healthz", responses=errors())
    def healthz() -> dict[str, Any]:
        try:
            ok = bool(conn.ping())
        except redis.RedisError:
            ok = False
        if not ok:
            raise HTTPException(503, detail="redis unreachable")
        return {"status": "ok"}

    @app.get("/metrics", response_class=Response, dependencies=secured, responses=errors(*auth))
    def metrics() -> Response:
        """Prometheus text format: jobs by status, batches merged, photons per second, merge
        latency, queue depth, workers alive."""
        return Response(metrics_body(), media_type=CONTENT_TYPE_LATEST)

    @app.get("/v1/workers", dependencies=secured, responses=errors(*auth))
    def list_workers() -> list[dict[str, Any]]:
        """Every registered worker: host, pid, state, last heartbeat, current job and batch."""
        return workers(jobs)

    @app.get("/v1/scenes", response_model=list[SceneSummary], dependencies=secured, responses=errors(*auth))
    def scenes() -> list[SceneSummary]:
        out = []
        for name in bundled_scene_names():
            description = json.loads(bundled_scene_path(name).read_text()).get("description", "")
            out.append(SceneSummary(name=name, description=description))
        return out

    @app.get("/v1/scenes/{name}", dependencies=secured, responses=errors(*auth, 404, 422))
    def scene(name: Annotated[str, PathParam(pattern=SCENE_NAME_PATTERN, max_length=MAX_SCENE_NAME)]) -> dict[str, Any]:
        try:
            return json.loads(bundled_scene_path(name).read_text())
        except SceneError as exc:
            raise HTTPException(404, detail=exc.message) from None

    loader = SceneLoader()

    def load_scene(request: SceneRequest, scene_loc: Callable[[SceneError], list[str | int]]) -> LoadedScene:
        """The scene loaded in a child process (service/scene_loader.py): a bad scene is a 422
        naming its field, one past the load's limits a 413, a load that cannot finish a 503."""
        try:
            return loader.load(request)
        except SceneLimitError as exc:
            raise HTTPException(413, detail=str(exc)) from None
        except SceneError as exc:
            raise _unprocessable(scene_loc(exc), exc.message) from None
        except LoadUnavailable as exc:
            raise HTTPException(503, detail=str(exc)) from None

    def create_job(loaded: LoadedScene, settings: JobSettings, scene_name: str | None,
                   scene_loc: Callable[[SceneError], list[str | int]], response: Response) -> JobView:
        """The one way a job is made (JSON body or upload) from its loaded scene: check the
        pixels, store the job with the scene's notes, issue its batches."""
        width, height = settings.resolution or loaded.resolution
        if width * height > MAX_SERVICE_PIXELS:
            raise _unprocessable(scene_loc(SceneError("camera.resolution", "")),
                                 f"at most {MAX_SERVICE_PIXELS} pixels per job")
        try:
            job_id = jobs.create(loaded.scene_json, Settings(**dict(settings)), width, height,
                                 scene_name, max_active=MAX_ACTIVE_JOBS, notes=loaded.notes)
        except JobLimitReached as exc:  # not the request's fault: the same request succeeds later
            raise HTTPException(429, detail=str(exc)) from None
        feed(jobs, job_id)
        response.headers["Location"] = f"/v1/jobs/{job_id}"
        log.info(f"job submitted: {scene_name or 'inline scene'} {width}x{height}", extra={"job": job_id})
        return job_view(jobs, existing(job_id))

    @app.post("/v1/jobs", status_code=201, response_model=JobView, dependencies=secured,
              responses=errors(*auth, 413, 422, 429))
    def submit(body: JobRequest, response: Response) -> JobView:
        def scene_loc(exc: SceneError) -> list[str | int]:
            if body.scene_name is not None:
                return ["body", "scene_name"]
            return ["body", "scene", *[int(p) if p.isdigit() else p for p in exc.field.split(".") if p]]
        loaded = load_scene(SceneRequest(scene_name=body.scene_name, scene=body.scene), scene_loc)
        return create_job(loaded, body.settings, body.scene_name, scene_loc, response)

    @app.post("/v1/jobs/upload", status_code=201, response_model=JobView, dependencies=secured,
              responses=errors(*auth, 413, 422, 429))
    def submit_upload(response: Response,
                      scene: Annotated[str, Form(description="the scene file inside the upload (.json or .xml)")],
                      archive: Annotated[UploadFile | None, File(description=".zip or .tar.gz of the scene "
                                                                             "and its meshes")] = None,
                      files: Annotated[list[UploadFile] | None, File(description="the scene and its meshes, "
                                                                                 "each named by its path")] = None,
                      settings: Annotated[str, Form(description="JobSettings as JSON")] = "{}") -> JobView:
        """A scene file with its mesh files (and included XML files) in one upload: an archive
        or several files. Limits apply to the unpacked upload (docs/limits.md); every file
        the scene names must lie inside it."""
        try:
            job_settings = JobSettings.model_validate_json(settings)
        except ValidationError as exc:
            raise HTTPException(422, detail=[{"loc": ["body", "settings", *e["loc"]], "msg": e["msg"],
                                              "type": e["type"]} for e in exc.errors()]) from None
        if (archive is None) == (not files):
            raise _unprocessable(["body", "archive"], "give exactly one of archive and files")
        with tempfile.TemporaryDirectory(prefix="photonfarm-upload-") as tmp:  # mode 0700
            root = Path(tmp).resolve()
            unpacker = Unpacker(root)
            try:
                if archive is not None:
                    unpacker.unpack("archive", archive.filename or "", archive.file)
                else:
                    for upload in files or []:
                        unpacker.write("files", upload.filename or "", upload.file)
                path = scene_path(root, scene)
            except UploadError as exc:
                if exc.status == 413:
                    raise HTTPException(413, detail=exc.message) from None
                raise _unprocessable(["body", exc.field], exc.message) from None

            def scene_loc(exc: SceneError) -> list[str | int]:
                return ["body", "scene", *([exc.field] if exc.field else [])]
            loaded = load_scene(SceneRequest(path=path, root=root), scene_loc)
            return create_job(loaded, job_settings, None, scene_loc, response)

    @app.get("/v1/jobs", response_model=list[JobView], dependencies=secured, responses=errors(*auth, 422))
    def list_jobs(response: Response, offset: int = Query(0, ge=0, le=MAX_LIST_OFFSET),
                  limit: int = Query(50, ge=1, le=500)) -> list[JobView]:
        """Jobs, newest first, a page at a time; X-Total-Count says how many there are."""
        records = (jobs.get(job_id) for job_id in jobs.ids(offset, limit, newest_first=True))
        response.headers["X-Total-Count"] = str(jobs.count())
        return [job_view(jobs, record) for record in records if record is not None]

    @app.get("/v1/jobs/{job_id}", response_model=JobView, dependencies=secured, responses=errors(*auth, 404))
    def job(job_id: str) -> JobView:
        return job_view(jobs, existing(job_id), history=True)

    @app.delete("/v1/jobs/{job_id}", response_model=JobView, status_code=202, dependencies=secured,
                responses={204: {"description": "the finished job and its images were deleted"},
                           **errors(*auth, 404)})
    def cancel_or_delete(job_id: str) -> Response | JobView:
        """An active job is cancelled (202: it stops within a pass and keeps its image); a
        finished one is deleted with its state and images (204)."""
        record = existing(job_id)
        if record.status in FINAL:
            jobs.delete(job_id)
            return Response(status_code=204)
        jobs.cancel(job_id)
        return job_view(jobs, existing(job_id))

    def validated(request: Request, record: JobRecord, kind: str, fmt: Literal["png", "exr"],
                  body_of: Callable[[JobRecord, Literal["png", "exr"]], tuple[bytes, dict[str, str]]]) -> Response:
        """An image or error map with its validator: a client holding the current tag gets
        a 304 without the state being read or encoded (RFC 9110, 13.1.2). A job with no pass
        folded, or an error map of a job that estimates none, has no tag to match (its answer
        is a blank image or a 409)."""
        has_tag = record.image_passes > 0 and (kind == "image" or record.settings.error_estimation)
        current = etag(record, kind, fmt, record.image_passes)
        if has_tag and current in if_none_match(request):
            return Response(status_code=304, headers={"ETag": current, "Cache-Control": "no-cache"})
        body, headers = body_of(record, fmt)
        tag = etag(record, kind, fmt, int(headers["X-Passes"]))  # the passes of the state it was made from
        return Response(body, media_type=MEDIA[fmt], headers={**headers, "ETag": tag, "Cache-Control": "no-cache"})

    @app.get("/v1/jobs/{job_id}/image", dependencies=secured,
             responses={200: {"content": {"image/png": {}, "image/x-exr": {}}, "headers": VALIDATOR_HEADERS},
                        304: NOT_MODIFIED, **errors(*auth, 404, 422)})
    def image(request: Request, job_id: str, format: Literal["png", "exr"] = Query("png")) -> Response:  # API name
        return validated(request, existing(job_id), "image", format, image_body)

    @app.get("/v1/jobs/{job_id}/error", dependencies=secured,
             responses={200: {"content": {"image/png": {}, "image/x-exr": {}}, "headers": VALIDATOR_HEADERS},
                        304: NOT_MODIFIED, **errors(*auth, 404, 409, 422)})
    def error_map(request: Request, job_id: str, format: Literal["png", "exr"] = Query("png")) -> Response:  # API name
        """PNG: relative error, colour-coded on a log scale (blue 0.1%, green 1%, yellow 10%,
        red 100%). EXR: the bias, noise and bound channels (luminance) and the relative error."""
        return validated(request, existing(job_id), "error", format, error_body)

    @app.get("/v1/jobs/{job_id}/pixel", response_model=PixelView, dependencies=secured,
             responses=errors(*auth, 404, 409, 422))
    def pixel(job_id: str, x: int = Query(ge=0), y: int = Query(ge=0)) -> PixelView:
        """One pixel's linear RGB and its error bound, from the job's current state (the PNG
        is tone-mapped and browsers read no EXR): the viewer's readout under the cursor."""
        record = existing(job_id)
        if x >= record.width:
            raise _unprocessable(["query", "x"], f"x must be below the width, {record.width}")
        if y >= record.height:
            raise _unprocessable(["query", "y"], f"y must be below the height, {record.height}")
        arrays = pixel_arrays(record)
        if arrays is None:
            raise HTTPException(409, detail="no pass merged yet")

        def value(name: str) -> float | None:  # none where unknown (an infinite bound) or not estimated
            v = float(arrays[name][y, x]) if name in arrays else math.nan
            return v if math.isfinite(v) else None
        return PixelView(x=x, y=y, passes=record.image_passes, rgb=tuple(float(v) for v in arrays["rgb"][y, x]),
                         luminance=value("luminance"), bound=value("bound"), relative_error=value("relative"),
                         measured=bool(arrays["measured"][y, x]) if "measured" in arrays else None,
                         confidence=record.settings.confidence if "relative" in arrays else None)

    return app


def app_from_env() -> FastAPI:
    """For `uvicorn service.app:app_from_env --factory`: the configuration's Redis URL and token."""
    settings = config()
    if settings.redis_url is None:
        raise ConfigError("REDIS_URL: unset (or REDIS_URL_FILE): the API needs a Redis")
    return create_app(settings.redis_url, settings.token)
