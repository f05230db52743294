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
SCENE_SECONDS = 400


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
def test_a_scene_uploaded_through_the_page_shows_cameras_points_training_and_views(page, server, shared_data):
    hall = shared_data / "unity_hall"
    page.goto("/#/new")
    drop_files(
        page,
        "#drop",
        sorted(hall.glob("*.png")) + sorted(hall.glob("matching*.txt")) + [hall / "calibration.txt"],
    )
    assert "5 photo(s), 4 match file(s), calibration: calibration.txt" in page.inner_text("#upload")
    page.select_option("#what", "scene")
    page.fill("input[name=steps]", "10")
    page.fill("input[name=orbit_frames]", "2")
    page.click("#submit")

    page.wait_for_selector("#scene[data-state=succeeded]", timeout=SCENE_SECONDS * 1000)
    scene = httpx.get(f"{server}/v1/scenes/{page.url.rsplit('/', 1)[-1]}").json()
    reconstruction_id, nerf_id = scene["stages"][0]["job_ids"][0], scene["stages"][1]["job_ids"][0]
    points = httpx.get(f"{server}/v1/jobs/{reconstruction_id}").json()["result"]["points"]
    view = page.wait_for_selector("#view3d[data-ready=true]", timeout=60_000)
    assert view.get_attribute("data-cameras") == "5" and view.get_attribute("data-points") == str(points)
    novel = page.wait_for_selector(f"#novel-{nerf_id}[data-renders='1']", timeout=60_000)
    novel.scroll_into_view_if_needed()
    box = novel.bounding_box()
    page.mouse.move(box["x"] + box["width"] / 2, box["y"] + box["height"] / 2)
    page.mouse.down()
    page.mouse.move(box["x"] + box["width"] / 2 + 40, box["y"] + box["height"] / 2, steps=4)
    page.mouse.up()
    # A second render after the drag (a selector: the page's CSP forbids the eval of wait_for_function).
    page.wait_for_selector(f"#novel-{nerf_id}[data-renders]:not([data-renders='1'])", timeout=60_000)
    page.wait_for_selector(f"#video-{nerf_id}", timeout=60_000)
    assert len(page.query_selector_all("#held-out img")) == 1  # LLFF hold-out of 5 photos: frame 0
    assert page.query_selector(f"#psnr-{nerf_id}") is not None
    page.wait_for_selector(f"#nerf-{nerf_id} tbody tr")  # the checkpoint list
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    page.screenshot(path=ARTIFACTS / "web_app_scene.png", full_page=True)

    page.goto(f"/#/jobs/{reconstruction_id}")  # the reconstruction's own job page
    page.wait_for_selector("#job[data-state=succeeded]")
    view = page.wait_for_selector("#view3d[data-ready=true]", timeout=60_000)
    assert view.get_attribute("data-cameras") == "5" and view.get_attribute("data-points") == str(points)
    page.wait_for_selector(f"#reconstruction-{reconstruction_id} figure img")
    assert "finished: succeeded" in page.inner_text(f"#log-{reconstruction_id}")
    page.screenshot(path=ARTIFACTS / "web_app_reconstruction_job.png", full_page=True)

    page.goto("/#/")
    assert (
        page.wait_for_selector(f"#scenes tr[data-id='{scene['id']}']").get_attribute("data-state")
        == "succeeded"
    )
    assert page.wait_for_selector(f"#jobs tr[data-id='{nerf_id}']").get_attribute("data-state") == "succeeded"
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
