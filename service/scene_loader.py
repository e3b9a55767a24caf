"""Scene loads for the API, each in a child process: reading, converting and validating a
scene (and inlining its meshes) never runs on a thread that serves requests, and a load
that runs past its wall-clock limit is killed.

A child is forked from a `forkserver` started on first use, never from the API process
itself, which holds threads and Redis connections that a fork would copy mid-use. The
forkserver imports the scene modules once, so each load starts in milliseconds. At most
`LOAD_PROCESSES` loads run at once and `LOAD_QUEUE` requests wait for one (within the same
wall-clock limit); a request past those is refused at once.
"""

from __future__ import annotations

import functools
import multiprocessing
import os
import threading
import time
from dataclasses import dataclass
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

from worker.scene import (
    SCENES_DIR,
    LoadBudget,
    SceneError,
    SceneLimitError,
    bundled_scene_path,
    inline_json,
    load_any_scene,
    load_scene_file,
    parse_scene,
)

LOAD_PROCESSES = 2  # loads at once; more wait (each is one CPU-bound process)
LOAD_QUEUE = 8  # requests that may wait for a load slot (the API serves on 40 threads)
LOAD_SECONDS = 60.0  # wall clock for one load, its wait for a slot included; then it is killed
EXIT_SECONDS = 5.0  # for a child that has answered to exit by itself
LOAD_NICENESS = 10  # a load yields the CPU to the threads that serve requests
PRELOAD = ["worker.scene", "worker.mitsuba_scene", "worker.meshes", "trimesh", "trimesh.exchange.ply",
           "trimesh.exchange.obj"]


@dataclass(frozen=True)
class LoadedScene:
    """A scene ready for a job: its JSON text (meshes inlined; encoded in the child, so the
    API's threads never decode or encode a large scene) and what the job needs to know of it."""

    scene_json: str
    resolution: tuple[int, int]
    notes: tuple[str, ...] = ()  # what the scene holds that was accepted but ignored, one line each


@dataclass(frozen=True)
class SceneRequest:
    """What to load: a bundled scene by name, a posted scene (JSON), or a file in an upload."""

    scene_name: str | None = None
    scene: dict[str, Any] | None = None
    path: Path | None = None
    root: Path | None = None


class LoadUnavailable(Exception):
    """The load was refused (loaders busy) or did not finish in time (the API answers 503)."""


def load_now(request: SceneRequest) -> LoadedScene:
    """The load itself, in this process, against one LoadBudget."""
    budget = LoadBudget()
    notes: list[str] = []
    if request.path is not None:
        assert request.root is not None
        parsed, base_dir = load_any_scene(request.path, root=request.root, budget=budget, notes=notes)
        root = request.root
    elif request.scene_name is not None:
        parsed, base_dir = load_scene_file(bundled_scene_path(request.scene_name), budget)
        root = SCENES_DIR
    else:
        parsed, base_dir, root = parse_scene(request.scene), SCENES_DIR, SCENES_DIR
    text = inline_json(parsed, base_dir, root, budget)
    return LoadedScene(text, parsed.camera.resolution, tuple(notes))


@functools.lru_cache(maxsize=64)
def _bundled(name: str) -> LoadedScene:
    """A bundled scene, loaded in this process (an unknown name raises SceneError, not cached)."""
    return load_now(SceneRequest(scene_name=name))


def _child(out: Connection, request: SceneRequest) -> None:
    """Runs in the child: sends ("ok", LoadedScene) or ("error", kind, field, message)."""
    os.nice(LOAD_NICENESS)
    try:
        result: tuple = ("ok", load_now(request))
    except SceneError as exc:  # sent as fields: SceneError's constructor takes two arguments
        result = ("error", type(exc).__name__, exc.field, exc.message)
    out.send(result)
    out.close()


class SceneLoader:
    """Owns the forkserver and bounds the loads in flight; `load` blocks its caller's thread
    (a request's worker thread) but holds no lock or GIL-bound work while it waits. At most
    `queue` requests wait for a slot; more are refused at once, so waiting loads never take
    all of the threads that serve requests."""

    def __init__(self, processes: int = LOAD_PROCESSES, seconds: float = LOAD_SECONDS,
                 queue: int = LOAD_QUEUE) -> None:
        self.seconds = seconds
        self.slots = threading.BoundedSemaphore(processes)
        self.admitted = threading.BoundedSemaphore(processes + queue)
        self._context: Any = None
        self._lock = threading.Lock()

    def _ctx(self) -> Any:
        with self._lock:  # created lazily: an app that never loads a scene starts no forkserver
            if self._context is None:
                self._context = multiprocessing.get_context("forkserver")
                self._context.set_forkserver_preload(PRELOAD)
            return self._context

    def load(self, request: SceneRequest) -> LoadedScene:
        """The loaded scene; SceneError (SceneLimitError past the budget) as the child raised
        it; LoadUnavailable if no slot came free or the load did not finish in time. A bundled
        scene is ours, small and unchanging: it is loaded once in this process and kept, so a
        burst of submits by name never waits for a loader."""
        if request.scene_name is not None and request.scene is None and request.path is None:
            return _bundled(request.scene_name)
        if not self.admitted.acquire(blocking=False):
            raise LoadUnavailable("every scene loader is busy and others wait for one: retry shortly")
        try:
            return self._load(request)
        finally:
            self.admitted.release()

    def _load(self, request: SceneRequest) -> LoadedScene:
        deadline = time.monotonic() + self.seconds
        if not self.slots.acquire(timeout=self.seconds):
            raise LoadUnavailable(f"every scene loader was busy for {self.seconds:g} s: retry shortly")
        try:
            ctx = self._ctx()
            receive, send = ctx.Pipe(duplex=False)
            child = ctx.Process(target=_child, args=(send, request), daemon=True)
            child.start()
            send.close()
            answered = False
            try:
                # The result is read before the child is joined: a large one fills the pipe.
                if not receive.poll(max(deadline - time.monotonic(), 0.0)):
                    raise LoadUnavailable(f"the scene did not load within {self.seconds:g} s")
                result = receive.recv()
                answered = True
            except EOFError:
                raise LoadUnavailable("the scene loader ended without an answer") from None
            finally:
                receive.close()
                child.join(EXIT_SECONDS if answered else 0.0)
                if child.is_alive():
                    child.kill()
                    child.join()
        finally:
            self.slots.release()
        if result[0] == "ok":
            return result[1]
        _, kind, field, message = result
        raise (SceneLimitError if kind == "SceneLimitError" else SceneError)(field, message)
