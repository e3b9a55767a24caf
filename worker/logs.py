"""Structured logs: one JSON object a line, with the job and batch ids a line concerns.

    log.info("batch merged", extra={"job": job_id, "batch": batch.id, "seconds": 1.9})
"""

from __future__ import annotations

import json
import logging
import time

CONTEXT_FIELDS = ("job", "batch", "worker", "reducer", "jobs", "outcome", "seconds", "passes", "reissued")


class JsonFormatter(logging.Formatter):
    def format(self, record: logging.LogRecord) -> str:
        entry = {"ts": time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(record.created)) + f".{int(record.msecs):03d}Z",
                 "level": record.levelname.lower(), "logger": record.name, "msg": record.getMessage()}
        entry.update({k: getattr(record, k) for k in CONTEXT_FIELDS if hasattr(record, k)})
        if record.exc_info:
            entry["error"] = self.formatException(record.exc_info)
        return json.dumps(entry)


def configure_logging(level: int = logging.INFO) -> None:
    handler = logging.StreamHandler()
    handler.setFormatter(JsonFormatter())
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(level)
