"""GET /metrics in Prometheus format, read from Redis at scrape time (so it counts every
worker process and survives API restarts), and the worker list behind GET /v1/workers."""

from __future__ import annotations

import time
from collections.abc import Iterator
from typing import Any

from prometheus_client import CollectorRegistry, generate_latest
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric, SummaryMetricFamily
from rq import Queue, Worker

from worker.scheduler import QUEUE_NAMES
from worker.store import Jobs, Status


def workers(jobs: Jobs) -> list[dict[str, Any]]:
    """Registered RQ workers with their last sign of life (our heartbeat thread's, every
    lease_seconds / 3 while the process lives; worker/heartbeat.py)."""
    beats = jobs.leases.heartbeats()
    now = time.time()
    out = []
    for w in Worker.all(connection=jobs.r):
        beat = beats.get(w.name, {})
        rq_seen = w.last_heartbeat.timestamp() if w.last_heartbeat else 0.0
        last_seen = max(rq_seen, float(beat.get("last_seen", 0.0)))
        out.append({"name": w.name, "hostname": w.hostname, "pid": w.pid, "state": str(w.get_state()),
                    "last_seen_seconds_ago": round(now - last_seen, 3), "alive": w.name in beats,
                    "job": beat.get("job") or None, "batch": beat.get("batch") or None,
                    "passes": int(beat.get("passes", 0)), "batches_done": w.successful_job_count})
    return sorted(out, key=lambda w: w["name"])


class ServiceCollector:
    def __init__(self, jobs: Jobs) -> None:
        self.jobs = jobs

    def collect(self) -> Iterator[Metric]:
        by_status = dict.fromkeys(Status, 0)
        merges = passes = photons = 0
        merge_seconds = rate = image_age = 0.0
        now = time.time()
        for job_id in self.jobs.ids():
            record = self.jobs.get(job_id)
            if record is None:
                continue
            by_status[record.status] += 1
            merges += record.merges
            merge_seconds += record.merge_seconds
            passes += record.passes
            photons += record.emitted
            if record.status == Status.RUNNING:
                rate += record.photons_per_second
                if record.passes > record.image_passes:  # accepted batches not yet in its image
                    image_age = max(image_age, now - max(record.folded_at, record.started or now))
        jobs = GaugeMetricFamily("photonfarm_jobs", "Jobs by status", labels=["status"])
        for status, count in by_status.items():
            jobs.add_metric([status.value], count)
        yield jobs
        yield CounterMetricFamily("photonfarm_batches_merged", "Batches merged into job states", value=merges)
        yield CounterMetricFamily("photonfarm_passes_merged", "Photon passes merged", value=passes)
        yield CounterMetricFamily("photonfarm_photons_emitted", "Photon paths of merged passes", value=photons)
        yield GaugeMetricFamily("photonfarm_photons_per_second", "Photon paths per second over running jobs",
                                value=rate)
        yield SummaryMetricFamily("photonfarm_merge_latency_seconds",
                                  "Time a merge takes (the delta pushed to the tiles and accepted)",
                                  count_value=merges, sum_value=merge_seconds)
        yield GaugeMetricFamily("photonfarm_image_age_seconds", "Largest time since the last fold over running "
                                "jobs with accepted batches not yet folded (the image's staleness)", value=image_age)
        depth = GaugeMetricFamily("photonfarm_queue_depth", "Batches waiting in a queue", labels=["queue"])
        for name in QUEUE_NAMES:
            depth.add_metric([name], Queue(name, connection=self.jobs.r).count)
        yield depth
        alive = sum(1 for w in workers(self.jobs) if w["alive"])
        yield GaugeMetricFamily("photonfarm_workers_alive", "Workers whose heartbeat is current", value=alive)


def metrics_text(jobs: Jobs) -> bytes:
    registry = CollectorRegistry(auto_describe=False)
    registry.register(ServiceCollector(jobs))
    return generate_latest(registry)
