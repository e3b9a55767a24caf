"""The reducer service over real processes (api_tests/cluster.py): a reducer SIGKILLed
mid-job hands the job to another, two API processes answer alike for one job, the job
progresses with the API down, and a batch that lands is in the served image within a
round. Every job ends with every pass counted exactly once (helpers.assert_exact)."""

from __future__ import annotations

import json
import subprocess
import time
from pathlib import Path

from api_tests.cluster import Cluster, finished
from api_tests.helpers import assert_exact
from worker.config import config
from worker.store import Jobs

PASSES, P = 40, 1 << 18  # a job of several batches (of about 2 s each) on a quiet machine too


def _long_job(c: Cluster, passes: int = PASSES) -> dict:
    """A job whose passes all cost what a uniform pass of P photons does (sampler auto's
    measuring chain passes are cheaper, and would shorten it unevenly)."""
    return c.submit(scene_name="cornell-box", settings={"max_passes": passes, "photons_per_pass": P,
                                                        "resolution": [96, 96], "seed": 9, "sampler": "uniform"})


def _owner(c: Cluster, job_id: str) -> subprocess.Popen | None:
    """The reducer process that last said it owns the job (its "jobs owned" log lines)."""
    owner = None
    for line in (c.data_dir / "reducers.log").read_text(errors="replace").splitlines():
        try:
            entry = json.loads(line)
        except ValueError:
            continue
        if entry.get("msg") == "jobs owned" and job_id in entry["jobs"]:
            owner = int(entry["reducer"].rsplit(":", 1)[1])
    return next((proc for proc in c.reducers if proc.pid == owner), None)


def test_a_reducer_killed_mid_job_hands_the_job_to_another(tmp_path: Path) -> None:
    c = Cluster(tmp_path, workers=2, reducers=2)
    passes = 4 * PASSES  # long enough to outlast the lease the takeover waits for
    try:
        job = _long_job(c, passes)
        c.wait(job["id"], lambda j: j["image_passes"] >= 2)
        owner = _owner(c, job["id"])
        assert owner is not None, "no reducer said it owns the job"
        c.kill_reducer(owner)
        shown = c.job(job["id"])["image_passes"]
        # The other reducer takes the job within a lease and its rounds go on.
        deadline = time.time() + 60
        while (survivor := _owner(c, job["id"])) is owner:
            assert time.time() < deadline, "no reducer took the job over"
            time.sleep(0.2)
        assert survivor is not None and survivor.poll() is None
        assert c.job(job["id"])["status"] == "running", "the job ended before the takeover: make it longer"
        c.wait(job["id"], lambda j: j["image_passes"] > shown, timeout=60)
        done = assert_exact(c, job["id"], passes, P, timeout=240)
        assert done["image_passes"] == passes
        assert c.http.get(job["links"]["image_exr"]).headers["x-passes"] == str(passes)
    finally:
        c.close()


def test_two_api_processes_answer_alike_for_one_job(tmp_path: Path) -> None:
    c = Cluster(tmp_path, workers=2)
    other = c.start_another_api()
    try:
        job = _long_job(c)
        c.wait(job["id"], lambda j: j["image_passes"] > 0)
        # Mid-job, the API that made the job and one that never saw it both serve the image.
        for http in (c.http, other):
            resp = http.get(job["links"]["image_exr"])
            assert resp.status_code == 200 and int(resp.headers["x-passes"]) > 0, resp.headers
        assert other.get(f"/v1/jobs/{job['id']}").json()["status"] in ("running", "completed")
        assert_exact(c, job["id"], PASSES, P, timeout=180)
        for link in ("image_exr", "image_png", "error_exr"):
            mine, theirs = c.http.get(job["links"][link]), other.get(job["links"][link])
            assert mine.status_code == theirs.status_code == 200
            assert mine.content == theirs.content and mine.headers["etag"] == theirs.headers["etag"], link
        pixel = {"x": 40, "y": 50}
        assert c.http.get(f"/v1/jobs/{job['id']}/pixel", params=pixel).json() == \
            other.get(f"/v1/jobs/{job['id']}/pixel", params=pixel).json()
        assert other.get(f"/v1/jobs/{job['id']}").json() == c.job(job["id"])
    finally:
        other.close()
        c.close()


def test_the_job_progresses_with_the_api_down(tmp_path: Path) -> None:
    c = Cluster(tmp_path, workers=2)
    try:
        job = _long_job(c)
        c.wait(job["id"], lambda j: j["image_passes"] > 0)
        c.kill_api()
        jobs = Jobs(c.redis_client)
        record, image = jobs.get(job["id"]), jobs.images.get(job["id"])
        assert record is not None and image is not None and record.passes < PASSES
        deadline = time.time() + 120
        while not ((now := jobs.images.get(job["id"])) and now.passes > image.passes):
            assert time.time() < deadline, "no new image published with the API down"
            time.sleep(0.2)
        assert jobs.get(job["id"]).passes > record.passes  # merged, folded and published without an API
        c.start_api()
        assert_exact(c, job["id"], PASSES, P, timeout=180)
    finally:
        c.close()


def test_a_batch_that_lands_is_in_the_served_image_within_a_round(tmp_path: Path) -> None:
    """A poll after a batch is accepted sees it once the reducer's next round is due
    (fold_seconds after the last) and done: here rounds of a small frame take milliseconds."""
    c = Cluster(tmp_path, workers=1)
    try:
        job = _long_job(c)
        jobs = Jobs(c.redis_client)
        bound = config().fold_seconds + config().fold_poll_seconds + 2.0  # the round's wait, a look, slack
        waits = []
        while len(waits) < 3:
            record = jobs.get(job["id"])
            if finished({"status": record.status}):
                break
            if record.passes <= record.image_passes:
                time.sleep(0.01)
                continue
            landed, start = record.passes, time.monotonic()  # accepted, not yet in the image
            while int(c.http.get(job["links"]["image_png"]).headers["x-passes"]) < landed:
                assert time.monotonic() - start < bound, f"the image lacked an accepted batch for {bound} s"
                time.sleep(0.05)
            waits.append(time.monotonic() - start)
        assert len(waits) == 3, f"only {len(waits)} batches seen landing: make the job longer"
        assert_exact(c, job["id"], PASSES, P, timeout=180)
    finally:
        c.close()
