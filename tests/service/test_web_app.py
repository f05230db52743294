"""The web app at `/` in a real browser (headless Chromium from the system's packages, driven by
Playwright): Unity Hall dropped on the upload page, the job followed to success, the 3D view showing its
cameras and points; API errors shown as messages. The job page's screenshot is kept as a test artifact."""

from __future__ import annotations

import base64
import os
from pathlib import Path

import httpx
import pytest
from playwright.sync_api import Page, sync_playwright

from tests.service.servers import ROOT, free_port, start_server

CHROMIUM = (
    "/usr/bin/chromium"  # Debian's package (scripts/test.sh installs it); Playwright's download is not used
)
ARTIFACTS = Path(os.environ.get("SFMNERF_TEST_ARTIFACTS", ROOT / "test-artifacts"))
JOB_SECONDS = 180


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    port = free_port()
    process = start_server(tmp_path_factory.mktemp("web") / "data", port)
    yield f"http://127.0.0.1:{port}"
    process.terminate()
    process.wait(timeout=30)


@pytest.fixture(scope="module")
def browser():
    with sync_playwright() as playwright:
        # SwiftShader gives headless Chromium WebGL without a GPU.
        chromium = playwright.chromium.launch(executable_path=CHROMIUM, args=["--enable-unsafe-swiftshader"])
        yield chromium
        chromium.close()


@pytest.fixture
def page(browser, server) -> Page:
    context = browser.new_context(viewport={"width": 1200, "height": 1300}, base_url=server)
    page = context.new_page()
    page.errors = []  # uncaught page errors, which the app must not have
    page.on("pageerror", lambda error: page.errors.append(str(error)))
    yield page
    context.close()


def drop_files(page: Page, selector: str, paths: list[Path]) -> None:
    """Drops files on an element as a person dragging them from a file manager does (a DataTransfer)."""
    files = [{"name": p.name, "data": base64.b64encode(p.read_bytes()).decode()} for p in paths]
    transfer = page.evaluate_handle(
        """files => {
            const transfer = new DataTransfer();
            for (const f of files) {
                const bytes = Uint8Array.from(atob(f.data), (c) => c.charCodeAt(0));
                transfer.items.add(new File([bytes], f.name));
            }
            return transfer;
        }""",
        files,
    )
    page.dispatch_event(selector, "drop", {"dataTransfer": transfer})


@pytest.mark.slow
def test_a_reconstruction_uploaded_through_the_page_shows_its_cameras_and_points(page, server, shared_data):
    hall = shared_data / "unity_hall"
    page.goto("/#/new")
    drop_files(
        page,
        "#drop",
        sorted(hall.glob("*.png")) + sorted(hall.glob("matching*.txt")) + [hall / "calibration.txt"],
    )
    assert "5 photo(s), 4 match file(s), calibration: calibration.txt" in page.inner_text("#upload")
    page.select_option("#what", "reconstruction")
    page.click("#submit")

    page.wait_for_selector("#job[data-state=succeeded]", timeout=JOB_SECONDS * 1000)
    view = page.wait_for_selector("#view3d[data-ready=true]", timeout=60_000)
    job_id = page.url.rsplit("/", 1)[-1]
    job = httpx.get(f"{server}/v1/jobs/{job_id}").json()
    assert view.get_attribute("data-cameras") == "5"
    assert view.get_attribute("data-points") == str(job["result"]["points"])
    page.wait_for_selector("#reconstruction-" + job_id + " figure img")
    assert "finished: succeeded" in page.inner_text(f"#log-{job_id}")
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    page.screenshot(path=ARTIFACTS / "web_app_reconstruction_job.png", full_page=True)

    page.goto("/#/")
    row = page.wait_for_selector(f"#jobs tr[data-id='{job_id}']")
    assert row.get_attribute("data-state") == "succeeded"
    assert page.errors == []


def test_api_errors_are_shown_as_readable_messages(page):
    page.goto("/#/jobs/0123456789abcdef0123456789abcdef")
    message = page.wait_for_selector("#error:not([hidden])").inner_text()
    assert "404" in message and "job 0123456789abcdef0123456789abcdef not found" in message
    assert "Traceback" not in page.content()
    page.goto("/#/new")
    page.click("#submit")  # nothing chosen: the service's 422 is shown, naming the field
    assert "images" in page.wait_for_selector("#error:not([hidden])").inner_text()
    assert page.errors == []


def test_the_token_is_kept_in_local_storage_and_sent(page, server):
    page.goto("/")
    page.fill("#token", "secret-token")
    page.dispatch_event("#token", "change")
    assert page.evaluate("localStorage.getItem('sfmnerf.token')") == "secret-token"
    with page.expect_request(lambda request: "/v1/jobs" in request.url) as sent:
        page.goto("/#/")
    assert sent.value.headers.get("authorization") == "Bearer secret-token"


def test_the_page_and_its_assets_come_from_the_service(server):
    index = httpx.get(f"{server}/")
    assert index.status_code == 200 and "importmap" in index.text
    for asset in ("app.js", "viewer.js", "style.css", "vendor/three/three.module.min.js",
                  "vendor/three/OrbitControls.js", "vendor/three/LICENSE"):  # fmt: skip
        assert httpx.get(f"{server}/static/{asset}").status_code == 200, asset
    assert "https://" not in index.text  # nothing from a CDN
