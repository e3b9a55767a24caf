"""The web page, driven in headless Chromium (Debian's chromium, through Playwright's
Python package; no browser is downloaded), against a real cluster: its start state, the
settings form (every JobSettings field), a job that converges with a live image and ticked,
labelled charts, the exposure control, 1:1 zoom with the pixel readout, ETA, the worker
list, cancel, delete, the paged job list, scene upload, and the layout at 800 px wide.
Screenshots of each state go to out/viewer/ (git-ignored, made anew by each run)."""

from __future__ import annotations

import json
import math
import re
from collections.abc import Iterator
from itertools import pairwise
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from api_tests.cluster import finished
from api_tests.helpers import CHROMIUM, CHROMIUM_FLAGS, zip_bytes
from service.client import eta_seconds
from service.models import JobSettings
from worker.image_io import read_channels
from worker.scene import SCENES_DIR

pytestmark = pytest.mark.skipif(CHROMIUM is None,
                                reason="Debian's chromium is not installed here (.ci/run installs it)")
SHOTS = Path(__file__).resolve().parent.parent / "out" / "viewer"  # git-ignored: a run leaves the tree clean
MITSUBA = SCENES_DIR / "mitsuba"
WIDE = {"width": 1400, "height": 1000}


@pytest.fixture(scope="module")
def page(cluster) -> Iterator:
    from playwright.sync_api import sync_playwright

    SHOTS.mkdir(parents=True, exist_ok=True)
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_FLAGS)
        pg = browser.new_page(viewport=WIDE, device_scale_factor=1)
        pg.goto(str(cluster.http.base_url) + "/")
        pg.wait_for_selector("#scene option", state="attached")
        pg.wait_for_selector("#set-method", state="attached")
        yield pg
        browser.close()


def _shot(page, name: str) -> None:
    page.screenshot(path=str(SHOTS / f"{name}.png"), full_page=True)


def _submit(page, scene: str, **fields: str) -> str:
    page.check("input[name=source][value=bundled]")
    page.select_option("#scene", scene)
    for selector, value in {"#set-error_threshold": "", "#set-max_seconds": "120", "#set-max_passes": "",
                            "#set-photons_per_pass": "16384", "#set-resolution": "", **fields}.items():
        page.fill(selector, value)
    return _click_render(page)


def _click_render(page) -> str:
    before = page.text_content("#job-id")
    page.click("#submit")
    page.wait_for_function(f"document.querySelector('#job-id').textContent !== {before!r}")
    return page.text_content("#job-id")


def _status(page, status: str, timeout: float = 120_000) -> None:
    page.wait_for_function(f"document.querySelector('#status').textContent === {status!r}", timeout=timeout)


def _full_id(cluster, prefix: str) -> str:
    ids = [j["id"] for j in cluster.http.get("/v1/jobs", params={"limit": 500}).json() if j["id"].startswith(prefix)]
    assert len(ids) == 1, ids
    return ids[0]


def test_start_state_has_no_broken_images_or_empty_frames(page) -> None:
    assert page.is_visible("#placeholder") and not page.is_visible("#job-panel")
    # Nothing visible that shows no picture: no image without pixels, no blank canvas or chart.
    blank = page.evaluate("""() => [...document.querySelectorAll('img, canvas, svg')]
        .filter(e => e.getClientRects().length > 0)
        .filter(e => e.tagName === 'IMG' ? !(e.complete && e.naturalWidth > 0)
                   : e.tagName === 'CANVAS' ? e.width === 0 || !e.dataset.passes : e.childElementCount === 0)
        .map(e => e.id)""")
    assert blank == []
    page.wait_for_function("document.querySelector('#jobs-range').textContent !== ''")  # the first poll
    assert page.text_content("#jobs-range") == "none yet"
    _shot(page, "start")


def test_page_lists_the_bundled_scenes(page) -> None:
    assert page.title() == "photonfarm"
    options = page.eval_on_selector_all("#scene option", "els => els.map(e => e.value)")
    assert {"cornell-caustics", "smallppm", "furnace"} <= set(options)


def test_the_form_has_every_job_setting_and_sends_them(page, cluster) -> None:
    ids = page.eval_on_selector_all("#settings [id^=set-]", "els => els.map(e => e.id.slice(4))")
    assert ids == list(JobSettings.model_fields), ids
    chosen = {"method": "ppm", "gather": "stochastic", "direct": "nee", "sampler": "adaptive", "priority": "high",
              "bias_constant": "dissertation"}
    for name, value in chosen.items():
        page.select_option(f"#set-{name}", value)
    typed = {"alpha": "0.6", "seed": "7", "hash_entries_per_photon": "2", "confidence": "0.8",
             "initial_radius": "3.5", "target_acceptance": "0.3"}
    short = _submit(page, "cornell-box", **{f"#set-{k}": v for k, v in typed.items()},
                    **{"#set-max_passes": "2", "#set-max_seconds": "", "#set-photons_per_pass": "4096",
                       "#set-resolution": "32x24"})
    job = cluster.http.get(f"/v1/jobs/{_full_id(cluster, short)}").json()
    expected = {**chosen, "alpha": 0.6, "seed": 7, "hash_entries_per_photon": 2.0, "confidence": 0.8,
                "target_acceptance": 0.3,
                "initial_radius": 3.5, "max_passes": 2, "photons_per_pass": 4096, "resolution": [32, 24],
                "error_estimation": True, "max_seconds": None, "error_threshold": None}
    assert {k: job["settings"][k] for k in expected} == expected
    _shot(page, "settings")
    _status(page, "completed")
    # back to the defaults the schema gives, for the tests below
    for name in [*chosen, *typed]:
        default = JobSettings.model_fields[name].default
        if name in chosen:
            page.select_option(f"#set-{name}", str(default))
        else:
            page.fill(f"#set-{name}", "" if default is None else str(default))


def test_job_from_the_page_converges_with_a_live_image_and_chart(page) -> None:
    _submit(page, "cornell-caustics", **{"#set-error_threshold": "0.1", "#set-resolution": "96x96"})
    page.wait_for_function("Number(document.querySelector('#image').dataset.passes || 0) >= 1", timeout=60_000)
    shown = page.get_attribute("#image", "data-passes")
    assert page.is_visible("#image") and not page.is_visible("#no-image")  # the image replaced the note
    first = page.locator("#image").screenshot()
    _shot(page, "running")
    page.wait_for_function(f"Number(document.querySelector('#image').dataset.passes) > {shown}", timeout=60_000)
    second = page.locator("#image").screenshot()
    assert first != second  # the estimate refined between the two screenshots
    _status(page, "converged")
    page.wait_for_timeout(1500)  # one more poll draws the last point
    assert page.locator("#chart-time circle.pt").count() >= 2
    assert page.locator("#chart-passes circle.pt").count() >= 2
    assert page.locator("#chart-time line.threshold").count() == 1
    _shot(page, "converged")
    radiance = page.locator("#image").screenshot()
    page.check("#errormap")
    page.wait_for_function("document.querySelector('#image').dataset.view === 'error'", timeout=10_000)
    assert page.locator("#image").screenshot() != radiance  # the relative-error map replaced the image
    _shot(page, "error-map")
    page.uncheck("#errormap")
    page.wait_for_function("document.querySelector('#image').dataset.view === 'image'", timeout=10_000)
    with page.expect_download() as download:
        page.click("#download-exr")
    assert download.value.suggested_filename.endswith(".exr")


def test_chart_axes_have_ticks_labels_and_a_labelled_threshold(page) -> None:
    """On the converged job above (threshold 10%)."""
    for chart, label in (("#chart-time", "seconds"), ("#chart-passes", "passes")):
        xs = [float(t) for t in page.eval_on_selector_all(f"{chart} text.xtick", "els => els.map(e => e.textContent)")]
        assert len(xs) >= 3 and xs[0] == 0 and all(b > a for a, b in pairwise(xs)), xs
        last = max(float(c) for c in page.eval_on_selector_all(
            f"{chart} circle.pt", "els => els.map(e => e.getAttribute('cx'))"))
        assert last <= float(page.get_attribute(f"{chart} line.axis", "x2")) + 1e-6  # every point on the axis
        ys = page.eval_on_selector_all(f"{chart} text.ytick", "els => els.map(e => e.textContent)")
        assert len(ys) >= 2 and "10%" in ys and "100%" in ys, ys
        assert page.text_content(f"{chart} text.xlabel") == label
        assert page.text_content(f"{chart} text.ylabel") == "relative error"
        assert page.text_content(f"{chart} text.threshold-label") == "threshold 10%"
        # the threshold line lies on the 10% tick
        tick = page.eval_on_selector_all(f"{chart} text.ytick", "els => els.filter(e => e.textContent === '10%')"
                                                                 ".map(e => Number(e.getAttribute('y')) - 3)")[0]
        assert abs(float(page.get_attribute(f"{chart} line.threshold", "y1")) - tick) < 1e-6


def _canvas_pixels(page) -> np.ndarray:
    data = page.evaluate("""() => { const c = document.querySelector('#image');
        return Array.from(c.getContext('2d').getImageData(0, 0, c.width, c.height).data); }""")
    return np.asarray(data, np.float64).reshape(-1, 4)[:, :3]


def _srgb_decode(s: np.ndarray) -> np.ndarray:
    return np.where(s <= 0.04045, s / 12.92, ((s + 0.055) / 1.055) ** 2.4)


def _srgb_encode(x: np.ndarray) -> np.ndarray:
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def test_exposure_scales_the_linear_radiance_of_the_shown_png(page) -> None:
    base = _canvas_pixels(page)
    page.fill("#exposure", "1")  # +1 EV: twice the radiance
    page.wait_for_function("document.querySelector('#image').dataset.exposure === '1'")
    brighter = _canvas_pixels(page)
    radiance = -np.log(1 - np.minimum(_srgb_decode(base / 255), 1 - 0.5 / 255))
    expected = np.round(255 * _srgb_encode(1 - np.exp(-2 * radiance)))
    assert np.abs(brighter - expected).max() <= 1  # canvas rounding
    assert brighter.mean() > base.mean() + 5
    _shot(page, "exposure-plus-1")
    page.fill("#exposure", "0")
    page.wait_for_function("document.querySelector('#image').dataset.exposure === '0'")
    assert np.array_equal(_canvas_pixels(page), base)


def test_zoom_1to1_and_the_pixel_under_the_cursor(page, cluster, tmp_path: Path) -> None:
    job = page.evaluate("state.job")
    page.select_option("#zoom", "1")
    page.locator("#image").scroll_into_view_if_needed()
    box = page.locator("#image").bounding_box()
    assert (box["width"], box["height"]) == (job["width"], job["height"])  # one image pixel a screen pixel
    x, y = 40, 67
    # the browser reports whole CSS pixels: point at the first whole one inside image pixel (x, y)
    page.mouse.move(math.ceil(box["x"] + x), math.ceil(box["y"] + y))
    page.wait_for_function(f"document.querySelector('#pixel-readout').dataset.x === '{x}' && "
                           f"document.querySelector('#pixel-readout').dataset.y === '{y}'", timeout=10_000)
    shown = json.loads(page.get_attribute("#pixel-readout", "data-rgb"))
    relative = float(page.get_attribute("#pixel-readout", "data-relative"))
    (tmp_path / "image.exr").write_bytes(cluster.http.get(job["links"]["image_exr"]).content)
    (tmp_path / "error.exr").write_bytes(cluster.http.get(job["links"]["error_exr"]).content)
    channels = read_channels(tmp_path / "image.exr")
    rgb = [float(channels[c][y, x]) for c in "RGB"]
    assert np.allclose(shown, rgb, rtol=1e-6, atol=0), (shown, rgb)  # the EXR stores float32
    assert math.isclose(relative, float(read_channels(tmp_path / "error.exr")["relative"][y, x]), rel_tol=1e-6)
    text = page.text_content("#pixel-readout")
    assert f"x {x}, y {y}: RGB" in text and "relative error" in text and "at 90% confidence" in text, text
    _shot(page, "zoom-1to1-readout")
    page.select_option("#zoom", "fit")  # fit: as wide as the panel allows, up to 512 px
    fit = page.locator("#image").bounding_box()
    assert fit["width"] == 512 and fit["height"] == 512 * job["height"] / job["width"], fit
    page.select_option("#zoom", "4")
    assert page.locator("#image").bounding_box()["width"] == 4 * job["width"]
    page.select_option("#zoom", "fit")


def test_the_pixel_endpoint_names_a_bad_coordinate(page, cluster) -> None:
    job = page.evaluate("state.job")
    link = f"/v1/jobs/{job['id']}/pixel"
    for query, field in (({"x": job["width"], "y": 0}, "x"), ({"x": 0, "y": job["height"]}, "y"),
                         ({"x": -1, "y": 0}, "x"), ({"x": 0}, "y")):
        resp = cluster.http.get(link, params=query)
        assert resp.status_code == 422 and resp.json()["detail"][0]["loc"] == ["query", field], resp.text
    assert cluster.http.get("/v1/jobs/nonesuch/pixel", params={"x": 0, "y": 0}).status_code == 404
    last = cluster.http.get(link, params={"x": job["width"] - 1, "y": job["height"] - 1}).json()
    now = cluster.http.get(f"/v1/jobs/{job['id']}").json()  # the job is final: its image holds every pass
    assert last["passes"] == now["image_passes"] == now["passes"] and len(last["rgb"]) == 3


def test_eta_is_the_clients(page) -> None:
    """The page's ETA against service/client.py's on the same job views."""
    history = [{"passes": i, "photons": 1000 * i, "seconds": 0.5 * i, "error": 0.4 * (0.5 * i) ** -0.5}
               for i in range(1, 11)]
    jobs: list[dict[str, Any]] = [
        {"settings": {"error_threshold": 0.05}, "error_history": history, "elapsed_seconds": 5.0, "passes": 10},
        {"settings": {"error_threshold": 0.05, "max_seconds": 30}, "error_history": history[:2],
         "elapsed_seconds": 1.0, "passes": 2},
        {"settings": {"max_passes": 40}, "error_history": [], "elapsed_seconds": 8.0, "passes": 10},
        {"settings": {}, "error_history": [], "elapsed_seconds": 8.0, "passes": 10},
    ]
    for job in jobs:
        mine = page.evaluate("job => etaSeconds(job)", job)
        theirs = eta_seconds(job)
        assert (mine is None) == (theirs is None) and (theirs is None or math.isclose(mine, theirs, rel_tol=1e-9)), \
            (job["settings"], mine, theirs)
    assert math.isclose(page.evaluate("job => etaSeconds(job)", jobs[0]), 0.4 ** 2 / 0.05 ** 2 - 5.0, rel_tol=1e-9)


def test_workers_eta_and_cancel_from_the_page(page, cluster) -> None:
    api_workers = cluster.http.get("/v1/workers").json()
    page.wait_for_function(f"document.querySelectorAll('#workers tbody tr').length === {len(api_workers)}")
    hosts = page.eval_on_selector_all("#workers td.host", "els => els.map(e => e.textContent)")
    assert sorted(hosts) == sorted(w["hostname"] for w in api_workers)
    beats = page.eval_on_selector_all("#workers td.beat", "els => els.map(e => e.textContent)")
    assert all(re.fullmatch(r"\d+\.\d s ago", b) for b in beats), beats
    short = _submit(page, "cornell-box", **{"#set-max_seconds": "300", "#set-resolution": "64x64"})
    page.wait_for_function("Number(document.querySelector('#image').dataset.passes || 0) >= 1", timeout=60_000)
    # a worker shows the job it renders, with the batch
    page.wait_for_function(f"[...document.querySelectorAll('#workers td.job')].some(e => e.textContent === '{short}')",
                           timeout=30_000)
    batch = page.eval_on_selector_all("#workers tr",
                                      f"rows => rows.filter(r => r.querySelector('td.job')?.textContent"
                                      f" === '{short}').map(r => r.querySelector('td.batch').textContent)")
    assert batch and batch[0] != "-"
    # ETA from the 300 s budget: between 0 and 300 s, and what the client says of the same view
    assert page.text_content("#status") == "running", page.text_content("#facts")
    eta = float(page.get_attribute("#eta", "data-seconds"))
    assert 0 < eta < 300 and re.fullmatch(r"\d+ s", page.text_content("#eta"))
    assert math.isclose(eta, eta_seconds(page.evaluate("state.job")), rel_tol=1e-9)
    _shot(page, "workers-and-eta")
    page.click("#cancel")
    _status(page, "cancelled", timeout=15_000)
    assert page.is_disabled("#cancel") and page.text_content("#eta") == "none: cancelled"


def test_delete_a_finished_job(page, cluster) -> None:
    """The job cancelled above: Delete answers 204, the job leaves the list and the page
    returns to its start state."""
    short = page.text_content("#job-id")
    job_id = _full_id(cluster, short)
    assert page.is_enabled("#delete")
    page.click("#delete")
    page.wait_for_selector("#placeholder", state="visible", timeout=10_000)
    assert cluster.http.get(f"/v1/jobs/{job_id}").status_code == 404
    page.wait_for_function("![...document.querySelectorAll('#jobs tr[data-id]')]"
                           f".some(r => r.dataset.id === '{job_id}')")


def test_the_job_list_pages(page, cluster) -> None:
    for _ in range(4):  # small jobs, so that there are more than one page of five
        cluster.submit(scene_name="furnace", settings={"max_passes": 1, "photons_per_pass": 1024, "resolution": [8, 8]})
    everything = [j["id"] for j in cluster.http.get("/v1/jobs", params={"limit": 500}).json()]
    total = len(everything)
    assert total > 5
    page.select_option("#page-size", "5")
    page.wait_for_function(f"document.querySelector('#jobs-range').textContent === '1-5 of {total}'")
    first = page.eval_on_selector_all("#jobs tr[data-id]", "rows => rows.map(r => r.dataset.id)")
    assert first == everything[:5] and page.is_disabled("#prev")
    _shot(page, "job-list-page-1")
    page.click("#next")
    page.wait_for_function("document.querySelector('#jobs-range').textContent.startsWith('6-')")
    second = page.eval_on_selector_all("#jobs tr[data-id]", "rows => rows.map(r => r.dataset.id)")
    assert second == everything[5:10] and page.is_enabled("#prev")
    page.click("#prev")
    page.wait_for_function("document.querySelector('#jobs-range').textContent.startsWith('1-')")
    page.select_option("#page-size", "10")


def test_upload_a_mitsuba_scene_from_the_page(page, cluster, tmp_path: Path) -> None:
    archive = zip_bytes({name: (MITSUBA / name).read_bytes()
                         for name in ("ply-mesh.xml", "room.xml", "meshes/icosphere.ply")})
    page.set_input_files("#upload-files",
                         files=[{"name": "scene.zip", "mimeType": "application/zip", "buffer": archive}])
    assert page.is_checked("input[name=source][value=upload]")  # choosing files picks the upload
    page.fill("#upload-scene", "ply-mesh.xml")
    for selector, value in {"#set-max_passes": "3", "#set-max_seconds": "", "#set-photons_per_pass": "4096",
                            "#set-resolution": "48x48"}.items():
        page.fill(selector, value)
    short = _click_render(page)
    _status(page, "completed")
    job = cluster.http.get(f"/v1/jobs/{_full_id(cluster, short)}").json()
    assert job["passes"] == 3 and job["photons"] == 3 * 4096 and (job["width"], job["height"]) == (48, 48)
    page.wait_for_function("document.querySelector('#image').dataset.passes === '3'", timeout=10_000)
    _shot(page, "uploaded-mitsuba-scene")
    # a bad scene: the service's one clear error, shown on the page
    text = (MITSUBA / "ply-mesh.xml").read_text().replace('<bsdf type="diffuse">', '<bsdf type="hair">', 1)
    (tmp_path / "bad.xml").write_text(text)
    (tmp_path / "room.xml").write_bytes((MITSUBA / "room.xml").read_bytes())
    page.set_input_files("#upload-files", files=[str(tmp_path / "bad.xml"), str(tmp_path / "room.xml")])
    page.fill("#upload-scene", "bad.xml")
    page.click("#submit")
    page.wait_for_function("document.querySelector('#submit-error').textContent.includes('unknown bsdf plugin')")
    assert page.text_content("#submit-error").startswith("HTTP 422: scene.bad.xml: line")
    _shot(page, "upload-error")
    # a folder: its files go by their paths inside it (the folder's name first)
    page.set_input_files("#upload-folder", MITSUBA)
    assert page.eval_on_selector("#upload-files", "e => e.files.length") == 0  # the folder replaced the files
    assert page.input_value("#upload-scene") == ""  # three scenes in the folder: the user names one
    page.fill("#upload-scene", "mitsuba/obj-mesh.xml")
    short = _click_render(page)
    _status(page, "completed")
    assert cluster.http.get(f"/v1/jobs/{_full_id(cluster, short)}").json()["photons"] == 3 * 4096
    page.check("input[name=source][value=bundled]")


def test_layout_holds_at_800px(page) -> None:
    page.set_viewport_size({"width": 800, "height": 1000})
    page.click("#jobs tr[data-id]")  # a job with an image
    page.wait_for_function("!document.querySelector('#image').hidden"
                           " && document.querySelector('#image').dataset.passes")
    page.wait_for_timeout(300)
    assert page.evaluate("document.documentElement.scrollWidth") <= 800
    outside = page.evaluate("""() => [...document.querySelectorAll('header, main, section, form, fieldset, table, '
        + '.pager, .controls, #frame, #image, .chart, #pixel-readout')]
        .filter(e => e.getClientRects().length > 0)
        .filter(e => { const r = e.getBoundingClientRect(); return r.left < 0 || r.right > 800 + 0.5; })
        .map(e => e.id || e.tagName)""")
    assert outside == []
    # one column: the viewer sits below the side panel, not squeezed beside it
    side, viewer = page.locator("#side").bounding_box(), page.locator("#viewer").bounding_box()
    assert viewer["y"] >= side["y"] + side["height"] and viewer["width"] > 700
    _shot(page, "narrow-800px")
    page.set_viewport_size(WIDE)


def test_the_browser_revalidates_an_unchanged_image(page, cluster) -> None:
    """The image comes with an ETag and no-cache: the page's second fetch of an unchanged image
    carries If-None-Match (the browser's cache adds it; viewer.js needs no code of its own)."""
    job = cluster.submit(scene_name="cornell-box", settings={"resolution": [16, 16], "photons_per_pass": 1024,
                                                              "max_passes": 2})
    cluster.wait(job["id"], lambda j: finished(j) and j["image_passes"] == j["passes"])
    url = job["links"]["image_png"]
    requests: list[Any] = []

    def record(request: Any) -> None:
        if url in request.url:
            requests.append(request)
    page.on("requestfinished", record)
    sizes = page.evaluate("async (u) => [(await (await api(u)).blob()).size, (await (await api(u)).blob()).size]", url)
    page.remove_listener("requestfinished", record)
    assert sizes[0] > 0 and sizes[0] == sizes[1]  # the page gets the image both times
    assert len(requests) == 2
    assert "if-none-match" not in requests[0].all_headers()
    # The second request names the first answer's tag; the server answers that with a 304
    # (test_api_contract), which the browser shows the page as its cached 200.
    assert requests[1].all_headers()["if-none-match"] == requests[0].response().all_headers()["etag"]
