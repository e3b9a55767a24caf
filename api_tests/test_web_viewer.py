"""The web page, driven in headless Chromium (Debian's chromium, through Playwright's
Python package; no browser is downloaded): it loads, a job submitted from it converges,
its image changes while the job renders, its error chart shows points, and cancel works."""

from __future__ import annotations

import shutil
from typing import Iterator

import pytest

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
pytestmark = pytest.mark.skipif(shutil.which("chromium") is None,
                                reason="Debian's chromium is not installed here (.ci/run installs it)")
FLAGS = ["--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run", "--disable-background-networking",
         "--disable-component-update", "--disable-sync"]


@pytest.fixture(scope="module")
def page(cluster) -> Iterator:  # noqa: ANN001
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=FLAGS)
        pg = browser.new_page(viewport={"width": 1400, "height": 900})
        pg.goto(str(cluster.http.base_url) + "/")
        pg.wait_for_selector("#scene option", state="attached")
        yield pg
        browser.close()


def _submit(page, scene: str, **fields: str) -> str:  # noqa: ANN001
    page.select_option("#scene", scene)
    for selector, value in {"#threshold": "0", "#max-seconds": "120", "#photons": "16384",
                            "#resolution": "", **fields}.items():
        page.fill(selector, value)
    before = page.text_content("#job-id")
    page.click("#submit")
    page.wait_for_function(f"document.querySelector('#job-id').textContent !== {before!r}")
    return page.text_content("#job-id")


def _status(page, status: str, timeout: float = 120_000) -> None:  # noqa: ANN001
    page.wait_for_function(f"document.querySelector('#status').textContent === {status!r}", timeout=timeout)


def test_page_lists_the_bundled_scenes(page) -> None:  # noqa: ANN001
    assert page.title() == "photonfarm"
    options = page.eval_on_selector_all("#scene option", "els => els.map(e => e.value)")
    assert {"cornell-caustics", "smallppm", "furnace"} <= set(options)


def test_job_from_the_page_converges_with_a_live_image_and_chart(page) -> None:  # noqa: ANN001
    _submit(page, "cornell-caustics", **{"#threshold": "0.1", "#resolution": "96x96"})
    page.wait_for_function("Number(document.querySelector('#image').dataset.passes || 0) >= 1", timeout=60_000)
    shown = page.get_attribute("#image", "data-passes")
    first = page.locator("#image").screenshot()
    page.wait_for_function(f"Number(document.querySelector('#image').dataset.passes) > {shown}", timeout=60_000)
    second = page.locator("#image").screenshot()
    assert first != second  # the estimate refined between the two screenshots
    _status(page, "converged")
    page.wait_for_timeout(1500)  # one more poll draws the last point
    assert page.locator("#chart-time circle.pt").count() >= 2
    assert page.locator("#chart-passes circle.pt").count() >= 2
    assert page.locator("#chart-time line.threshold").count() == 1
    radiance = page.locator("#image").screenshot()
    page.check("#errormap")
    page.wait_for_function("document.querySelector('#image').dataset.view === 'error'", timeout=10_000)
    assert page.locator("#image").screenshot() != radiance  # the relative-error map replaced the image
    with page.expect_download() as download:
        page.click("#download-exr")
    assert download.value.suggested_filename.endswith(".exr")


def test_cancel_from_the_page(page) -> None:  # noqa: ANN001
    _submit(page, "cornell-box", **{"#max-seconds": "300", "#resolution": "64x64"})
    page.wait_for_function("Number(document.querySelector('#image').dataset.passes || 0) >= 1", timeout=60_000)
    page.click("#cancel")
    _status(page, "cancelled", timeout=15_000)
    assert page.is_disabled("#cancel")
