"""Every tunable of photonfarm in one object, `Config`, read from the environment once.

Each field declares its environment variable, default, format and meaning (`setting`);
`VARIABLES` lists them in declaration order: docs/hooks/reference.py builds the
documentation's table from it and tests/test_reference_docs.py holds the code to it.
`config()` reads the process's environment on first use and keeps the result; no module
reads these variables itself, nor keeps a value at import. Tests build their own `Config`
(`dataclasses.replace(config(), ...)`) and install it with `use`.

A secret (the API token, the Redis URL with its password) may instead be given in a file
named by the same variable with `_FILE` appended, as Docker secrets are mounted: never on a
command line, which any local user can read. Importable without OpenCL.
"""

from __future__ import annotations

import dataclasses
import math
import os
import types
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Union, get_args, get_origin, get_type_hints
from urllib.parse import urlsplit

URL_SCHEMES = ("redis", "rediss", "unix")
FILE_SUFFIX = "_FILE"  # VAR_FILE=path: the secret VAR is the file's content (surrounding whitespace stripped)


class ConfigError(ValueError):
    """A variable's value refused; the message is one line that names the variable."""


def setting(env: str, default: Any, format: str, meaning: str, check: Callable[[Any], bool] | None = None,
            secret: bool = False) -> Any:
    """A `Config` field read from the variable `env`: `default` when it is unset or empty,
    else its value parsed as the field's type and accepted by `check`; `format` says what a
    value may be. A secret is never echoed in an error and may come from `env` + _FILE."""
    return field(default=default, metadata={"env": env, "format": format, "meaning": meaning, "check": check,
                                            "secret": secret})


def _positive(value: float) -> bool:
    return value > 0 and math.isfinite(value)


def _share(value: float) -> bool:
    return 0 < value <= 1


def _not_negative(value: float) -> bool:
    return value >= 0 and math.isfinite(value)


def _redis_urls(value: str | tuple[str, ...]) -> bool:
    return all(urlsplit(u).scheme in URL_SCHEMES for u in ((value,) if isinstance(value, str) else value))


@dataclass(frozen=True)
class Config:
    """The tunables. Derived values are properties: they follow the fields they come from."""

    # ---------------------------------------------------------------- deployment
    data: Path = setting("PHOTONFARM_DATA", Path("data"), "a directory path",
                         "`photonfarm serve`'s default `--data-dir`: where the embedded Redis keeps its password "
                         "and append-only file")
    redis_url: str | None = setting("REDIS_URL", None, "a `redis://`, `rediss://` or `unix://` URL",
                                    "the Redis that holds queues, records and leases, password included; unset: "
                                    "`photonfarm serve` starts an embedded one", _redis_urls, secret=True)
    token: str | None = setting("PHOTONFARM_TOKEN", None, "any non-empty string",
                                "the API's bearer token: when set, every data route wants `Authorization: Bearer "
                                "<token>`; `photonfarm submit` sends it. `serve` binds beyond loopback only with "
                                "one", secret=True)
    url: str = setting("PHOTONFARM_URL", "http://127.0.0.1:8000", "an http(s) URL",
                       "`photonfarm submit`'s default `--url`: the API it talks to")
    redis_maxmemory: str = setting("PHOTONFARM_REDIS_MAXMEMORY", "4gb", "a Redis memory size (`4gb`, `512mb`, bytes)",
                                   "the embedded Redis's memory cap, no eviction: a full Redis refuses writes "
                                   "(HTTP 507)")
    state_urls: tuple[str, ...] = setting("PHOTONFARM_STATE_URLS", (), "comma-separated Redis URLs, the same list "
                                          "in the same order for the API and every worker",
                                          "the Redis nodes that hold job states (tile k on node k mod n); unset: "
                                          "the main Redis (`REDIS_URL`) holds them", _redis_urls,
                                          secret=True)
    host_threads: int = setting("PHOTONFARM_HOST_THREADS", 1, "an integer; values below 1 count as 1",
                                "threads a process spreads its host-side tile work over (a fold round's deltas, "
                                "its error estimate, pushes to the state nodes)")
    worker_nice: int = setting("PHOTONFARM_WORKER_NICE", 10, "an integer (added to the process's niceness)",
                               "how much lower a worker's CPU priority is than the process that started it, so "
                               "that the reducers' fold rounds and Redis come first on a shared machine")
    tile_pixels: int = setting("PHOTONFARM_TILE_PIXELS", 1 << 16, "a positive integer",
                               "pixels per state tile for jobs created from now on (a job keeps its tile size)",
                               _positive)
    tile_cache_mb: float = setting("PHOTONFARM_TILE_CACHE_MB", 2048.0, "megabytes (10^6 bytes), a number",
                                   "folded state tiles a process keeps in memory to read without a round trip "
                                   "(the default holds a 3840 x 2160 job's state)", _not_negative)
    retention_seconds: float = setting("PHOTONFARM_RETENTION_SECONDS", 7 * 86_400.0, "seconds, a positive number",
                                       "how long a finished job and its images are kept before they are deleted "
                                       "(7 days)", _positive)
    # ---------------------------------------------------------------- batches and leases
    lease_seconds: float = setting("PHOTONFARM_LEASE_SECONDS", 30.0, "seconds, a positive number",
                                   "a batch's lease: a started batch whose worker is not heard from this long is "
                                   "re-issued; heartbeats every third of it, a worker unheard for three leases "
                                   "counts as gone; also the fold lease", _positive)
    max_attempts: int = setting("PHOTONFARM_MAX_ATTEMPTS", 3, "a positive integer",
                                "a batch that fails this often fails its job", _positive)
    max_inflight_per_job: int = setting("PHOTONFARM_MAX_INFLIGHT_PER_JOB", 256, "a positive integer",
                                        "workers one job may keep busy at once", _positive)
    batch_target_seconds: float = setting("PHOTONFARM_BATCH_TARGET_SECONDS", 2.0, "seconds, a positive number",
                                          "a batch's passes are chosen to take about this long, within the "
                                          "shares below", _positive)
    merge_share: float = setting("PHOTONFARM_MERGE_SHARE", 0.05, "a share in (0, 1]",
                                 "a batch lasts at least its merge and its job's fold round over this share",
                                 _share)
    merge_path_share: float = setting("PHOTONFARM_MERGE_PATH_SHARE", 0.5, "a share in (0, 1]",
                                      "a job's merges keep the state nodes busy at most this share of the time "
                                      "(N workers: a batch lasts N mean merges over it)", _share)
    pass_slack: float = setting("PHOTONFARM_PASS_SLACK", 0.5, "a number, 0 or more",
                                "batches are planned to deliver within the refresh even when their passes run "
                                "this much slower than the recent ones", _not_negative)
    # ---------------------------------------------------------------- the fold
    refresh_seconds: float = setting("PHOTONFARM_REFRESH_SECONDS", 10.0, "seconds, a positive number",
                                     "the image a client sees is at most about this old", _positive)
    fold_seconds: float = setting("PHOTONFARM_FOLD_SECONDS", 2.0, "seconds, a positive number",
                                  "the least time from one fold round of a job to the next", _positive)
    fold_share: float = setting("PHOTONFARM_FOLD_SHARE", 0.1, "a share in (0, 1]",
                                "a job's fold rounds take at most this share of the time, as far as the refresh "
                                "allows", _share)
    fold_poll_seconds: float = setting("PHOTONFARM_FOLD_POLL_SECONDS", 0.5, "seconds, a positive number",
                                       "a reducer looks at its jobs this often, and at once on news", _positive)
    fold_wait_min_seconds: float = setting("PHOTONFARM_FOLD_WAIT_MIN_SECONDS", 0.05, "seconds, a positive number",
                                           "a reducer looks at once when a job's round is due, but not more "
                                           "often than this", _positive)
    fold_stale_seconds: float = setting("PHOTONFARM_FOLD_STALE_SECONDS", 5.0, "seconds, a number",
                                        "a worker folds after its merge when no reducer has folded this long past "
                                        "the image's planned time")
    rounds_kept: int = setting("PHOTONFARM_ROUNDS_KEPT", 8, "a positive integer",
                               "a job's recent fold rounds that predict the next one's length", _positive)
    round_margin: float = setting("PHOTONFARM_ROUND_MARGIN", 2.0, "a number, 0 or more",
                                  "the prediction adds this many times the most a recent round ran over it",
                                  _not_negative)
    checkpoint_seconds: float = setting("PHOTONFARM_CHECKPOINT_SECONDS", 30.0, "seconds, 0 or more",
                                        "a round writes every tile once a folded batch's delta has been pending "
                                        "this long", _not_negative)
    checkpoint_pending_share: float = setting("PHOTONFARM_CHECKPOINT_PENDING_SHARE", 0.5, "a positive number",
                                              "a round writes the tiles that keep the deltas pending within this "
                                              "share of the state's bytes", _positive)
    checkpoint_held_share: float = setting("PHOTONFARM_CHECKPOINT_HELD_SHARE", 1.0, "a positive number",
                                           "past this share of the state's bytes in pending deltas a round writes "
                                           "tiles whatever that takes", _positive)
    end_handoff_seconds: float = setting("PHOTONFARM_END_HANDOFF_SECONDS", 3.0, "seconds, a positive number",
                                         "the worker whose batch decides a job's end ends it itself if no folder "
                                         "has begun to within this long", _positive)
    end_handoff_poll_seconds: float = setting("PHOTONFARM_END_HANDOFF_POLL_SECONDS", 0.05,
                                              "seconds, a positive number",
                                              "how often that worker looks whether a folder has begun", _positive)

    @property
    def queued_seconds(self) -> float:
        """How often the reaper checks that a waiting batch is still in its queue."""
        return self.lease_seconds

    @property
    def fold_lease_seconds(self) -> float:
        """The lease a job's one folder holds, renewed per tile."""
        return self.lease_seconds

    @property
    def alive_seconds(self) -> float:
        """A worker process not heard from this long is dead: no capacity, its leases lapse."""
        return 3 * self.lease_seconds

    @property
    def delivery_seconds(self) -> float:
        """A job's batches are delivered at most this far apart: an image change follows each
        by the folder's next look and its round."""
        return self.refresh_seconds - self.fold_poll_seconds

    @property
    def planned_delivery_seconds(self) -> float:
        """Deliveries as planned at the recent pace, leaving room for passes pass_slack slower."""
        return self.delivery_seconds / (1.0 + self.pass_slack)

    @property
    def tile_cache_bytes(self) -> int:
        return int(self.tile_cache_mb * 1e6)

    @classmethod
    def from_environ(cls, environ: Mapping[str, str]) -> Config:
        """The configuration `environ` gives, or ConfigError naming the first bad variable."""
        hints = get_type_hints(cls)
        values = {}
        for f in dataclasses.fields(cls):
            text = _raw(environ, f.metadata["env"], f.metadata["secret"])
            if text is not None:
                values[f.name] = _parse(f, hints[f.name], text)
        return cls(**values)


@dataclass(frozen=True)
class Variable:
    """One environment variable as the documentation lists it."""

    name: str
    field: str
    default: Any
    format: str
    meaning: str
    secret: bool


VARIABLES: tuple[Variable, ...] = tuple(
    Variable(f.metadata["env"], f.name, f.default, f.metadata["format"], f.metadata["meaning"], f.metadata["secret"])
    for f in dataclasses.fields(Config))


def _raw(environ: Mapping[str, str], name: str, secret: bool) -> str | None:
    """A variable's text (for a secret, or else its _FILE's content); None when unset or empty."""
    text = environ.get(name, "").strip()
    path = environ.get(name + FILE_SUFFIX, "").strip() if secret else ""
    if text and path:
        raise ConfigError(f"{name} and {name}{FILE_SUFFIX} are both set: give one")
    if path:
        try:
            text = Path(path).read_text().strip()
        except (OSError, UnicodeDecodeError) as exc:
            raise ConfigError(f"{name}{FILE_SUFFIX}: cannot read {path}: {exc.__class__.__name__}") from None
        if not text:
            raise ConfigError(f"{name}{FILE_SUFFIX}: {path} is empty")
    return text or None


def _parse(f: dataclasses.Field, kind: Any, text: str) -> Any:
    """`text` as the field's type (an optional type as its other member; a tuple of strings
    from a comma-separated list), checked; ConfigError naming the variable otherwise."""
    name = f.metadata["env"]
    if get_origin(kind) in (Union, types.UnionType):
        kind = next(k for k in get_args(kind) if k is not type(None))
    try:
        if kind == tuple[str, ...]:
            value: Any = tuple(u.strip() for u in text.split(",") if u.strip())
        elif kind is int:
            value = int(text)
        else:
            value = kind(text)
    except ValueError:
        value = None
    check = f.metadata["check"]
    if value is None or (check is not None and not check(value)):
        shown = "" if f.metadata["secret"] else f": got {text[:80]!r}"
        raise ConfigError(f"{name}: expected {f.metadata['format']}{shown}")
    return value


_active: Config | None = None


def config() -> Config:
    """The process's configuration: read from its environment on first use, then kept."""
    global _active
    if _active is None:
        _active = Config.from_environ(os.environ)
    return _active


def use(new: Config | None) -> None:
    """Install a configuration (tests); None: read the environment again on next use."""
    global _active
    _active = new
