"""A module and a callable that a queued job could name, each leaving a file behind when
imported or called (in the directory PHOTONFARM_TRIPWIRE_DIR names): a directory left
empty proves a worker neither imported nor ran them."""

from __future__ import annotations

import os
import uuid
from pathlib import Path
from typing import Any

DIR_ENV = "PHOTONFARM_TRIPWIRE_DIR"

if os.environ.get(DIR_ENV):
    (Path(os.environ[DIR_ENV]) / f"imported-{os.getpid()}").touch()


def spring(*args: Any, **kwargs: Any) -> None:
    """Leave a file: the caller ran a function it was named by a queued job."""
    (Path(os.environ[DIR_ENV]) / f"called-{uuid.uuid4().hex}").touch()
