"""Every PHOTONFARM_* environment variable, declared once: name, default, format and meaning.

This is the declaration the documentation's table is generated from and that
tests/test_reference_docs.py holds against the code; the modules named in `read_by` read
the variables themselves, at import or at start. Importable without OpenCL.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Variable:
    """One environment variable. `default` is the value used when it is unset or empty
    (None: the feature is off); `format` says what a value may be."""

    name: str
    default: str | None
    format: str
    meaning: str
    read_by: str


VARIABLES: tuple[Variable, ...] = (
    Variable("PHOTONFARM_DATA", "data", "a directory path",
             "`photonfarm serve`'s default `--data-dir`: where the embedded Redis keeps its password and "
             "append-only file", "service/cli.py"),
    Variable("PHOTONFARM_HOST_THREADS", "1", "an integer; values below 1 count as 1",
             "threads a process spreads its host-side tile work over (a fold round's deltas, its error "
             "estimate, pushes to the state nodes)", "worker/host_threads.py"),
    Variable("PHOTONFARM_LEASE_SECONDS", "30", "seconds, a positive number",
             "a batch's lease: a started batch whose worker is not heard from this long is re-issued; "
             "heartbeats every third of it, a worker unheard for three leases counts as gone",
             "worker/store/policy.py"),
    Variable("PHOTONFARM_REDIS_MAXMEMORY", "4gb", "a Redis memory size (`4gb`, `512mb`, bytes)",
             "the embedded Redis's memory cap, no eviction: a full Redis refuses writes (HTTP 507)",
             "service/redis_server.py"),
    Variable("PHOTONFARM_RETENTION_SECONDS", "604800", "seconds, a positive number",
             "how long a finished job and its images are kept before they are deleted (7 days)",
             "worker/store/policy.py"),
    Variable("PHOTONFARM_STATE_URLS", None, "comma-separated Redis URLs, the same list in the same order "
             "for the API and every worker",
             "the Redis nodes that hold job states (tile k on node k mod n); unset: the main Redis "
             "(`REDIS_URL`) holds them", "worker/store/tiles.py"),
    Variable("PHOTONFARM_TILE_CACHE_MB", "2048", "megabytes (10^6 bytes), a number",
             "folded state tiles a process keeps in memory to read without a round trip",
             "worker/store/tiles.py"),
    Variable("PHOTONFARM_TILE_PIXELS", "65536", "a positive integer",
             "pixels per state tile for jobs created from now on (a job keeps its tile size)",
             "worker/store/tiles.py"),
    Variable("PHOTONFARM_TOKEN", None, "any non-empty string",
             "the API's bearer token: when set, every data route wants `Authorization: Bearer <token>`; "
             "`photonfarm submit` sends it", "service/cli.py, service/app.py, service/client.py"),
    Variable("PHOTONFARM_URL", "http://127.0.0.1:8000", "an http(s) URL",
             "`photonfarm submit`'s default `--url`: the API it talks to", "service/client.py"),
    Variable("PHOTONFARM_WORKER_NICE", "10", "an integer (added to the process's niceness)",
             "how much lower a worker's CPU priority is than the process that started it, so that the "
             "API's fold rounds and Redis come first on a shared machine", "worker/queue_worker.py"),
)
