"""The web app at `/` in a real browser (headless Chromium from the system's packages, driven by
Playwright): Unity Hall dropped on the upload page, the job followed to success, the 3D view showing its
cameras and points, the novel view opening at a registered camera; API errors shown as messages. Every page
runs under a strict Content-Security-Policy (no inline script or style, no eval) and must not break it.
The scene and job pages' screenshots are kept as test artifacts."""

from __future__ import annotations

import base64
import json
import os
import re
import time
from pathlib import Path

import httpx
import numpy as np
import pytest
from playwright.sync_api import Page, sync_playwright

from tests.service.servers import ROOT, free_port, start_server

CHROMIUM = (
    "/usr/bin/chromium"  # Debian's package (scripts/test.sh installs it); Playwright's download is not used
)
ARTIFACTS = Path(os.environ.get("SFMNERF_TEST_ARTIFACTS", ROOT / "test-artifacts"))
SCENE_SECONDS = 400
WEB_DIR = ROOT / "service" / "web"
# The strictest policy the app runs under: its own scripts, styles and API only; images also from the blob:
# URLs it makes of API responses (they need the token, so no plain src= link).
STRICT_CSP = (
    "default-src 'self'; script-src 'self'; style-src 'self'; img-src 'self' blob:; connect-src 'self'; "
    "object-src 'none'; base-uri 'none'; form-action 'self'; frame-ancestors 'none'"
)


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


def with_strict_csp(route) -> None:
    """The page as the service sends it, under STRICT_CSP (whatever policy the service adds applies too)."""
    response = route.fetch()
    route.fulfill(response=response, headers={**response.headers, "content-security-policy": STRICT_CSP})


@pytest.fixture
def page(browser, server) -> Page:
    context = browser.new_context(viewport={"width": 1200, "height": 1300}, base_url=server)
    page = context.new_page()
    page.route(re.compile(r"^[^#]*://[^/]+/(#.*)?$"), with_strict_csp)
    page.errors = []  # uncaught page errors and CSP violations, which the app must not have
    page.on("pageerror", lambda error: page.errors.append(str(error)))
    def on_console(message) -> None:
        if "Content Security Policy" in message.text:
            page.errors.append(message.text)

    page.on("console", on_console)
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


def wait_for_renders(novel, count: int, seconds: float = 60.0) -> None:
    """Until the novel view has shown `count` renders (polled here: the page's CSP forbids the string
    evaluation that wait_for_function uses)."""
    deadline = time.monotonic() + seconds
    while int(novel.get_attribute("data-renders")) < count:
        assert time.monotonic() < deadline, f"{novel.get_attribute('data-renders')} renders, {count} expected"
        time.sleep(0.2)


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
    page.fill("input[name=train_max_side]", "200")
    page.click("#submit")

    renders = []  # the novel view's render requests
    page.on("request", lambda request: renders.append(request) if request.url.endswith("/render") else None)
    page.wait_for_selector("#scene[data-state=succeeded]", timeout=SCENE_SECONDS * 1000)
    scene = httpx.get(f"{server}/v1/scenes/{page.url.rsplit('/', 1)[-1]}").json()
    reconstruction_id, nerf_id = scene["stages"][0]["job_ids"][0], scene["stages"][1]["job_ids"][0]
    points = httpx.get(f"{server}/v1/jobs/{reconstruction_id}").json()["result"]["points"]
    view = page.wait_for_selector("#view3d[data-ready=true]", timeout=60_000)
    assert view.get_attribute("data-cameras") == "5" and view.get_attribute("data-points") == str(points)
    novel = page.wait_for_selector(f"#novel-{nerf_id}[data-renders='1']", timeout=60_000)
    # It opens at a registered camera's pose (OpenGL camera-to-world [R^T diag(1,-1,-1) | C]), on the path.
    assert novel.get_attribute("data-mode") == "path"
    first_request = json.loads(renders[0].post_data)
    assert first_request["frame"] == "data"  # the registered cameras' own frame, not the capture frame
    first_pose = np.array(first_request["c2w"])
    cameras = httpx.get(f"{server}/v1/reconstructions/{reconstruction_id}").json()["cameras"]
    distances = [
        np.abs(first_pose[:3] - np.c_[np.array(c["R"]).T @ np.diag([1.0, -1.0, -1.0]), c["C"]]).max()
        for c in cameras
    ]
    assert min(distances) < 1e-6, distances
    assert page.inner_text(f"#novel-label-{nerf_id}").startswith("near photo ")
    novel.scroll_into_view_if_needed()
    box = novel.bounding_box()
    page.mouse.move(box["x"] + box["width"] / 2, box["y"] + box["height"] / 2)
    page.mouse.down()
    page.mouse.move(box["x"] + box["width"] / 2 + 40, box["y"] + box["height"] / 2, steps=4)
    page.mouse.up()
    wait_for_renders(novel, 2)
    page.check(f"#free-{nerf_id}")  # the free orbit, from where the camera is
    page.wait_for_selector(f"#novel-label-{nerf_id}:text-matches('^free orbit: ')", timeout=60_000)
    assert novel.get_attribute("data-mode") == "free" and "eye" in json.loads(renders[-1].post_data)
    page.uncheck(f"#free-{nerf_id}")  # back among the photos, as the screenshot shows the page by default
    page.wait_for_selector(f"#novel-label-{nerf_id}:text-matches('^near photo ')", timeout=60_000)
    page.wait_for_selector(f"#video-{nerf_id}", timeout=60_000)
    train_size = httpx.get(f"{server}/v1/nerf/{nerf_id}").json()["config"]["camera"]
    assert max(train_size["width"], train_size["height"]) == 200  # the form's training photo size
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
    assert index.status_code == 200 and '<script type="module" src="/static/app.js"></script>' in index.text
    assert "https://" not in index.text  # nothing from a CDN
    # Nothing inline that a strict CSP refuses: scripts (an import map is one), handlers, style attributes.
    assert re.findall(r"<script(?![^>]*\bsrc=)[^>]*>|\son\w+=|\sstyle=", index.text) == []
    for asset in ("style.css", "favicon.svg", "vendor/three/LICENSE"):
        assert httpx.get(f"{server}/static/{asset}").status_code == 200, asset
    modules = sorted(WEB_DIR.rglob("*.js"))
    assert len(modules) > 10
    for module in modules:  # browsers run module scripts only when served as JavaScript
        response = httpx.get(f"{server}/static/{module.relative_to(WEB_DIR).as_posix()}")
        assert response.status_code == 200, module
        assert response.headers["content-type"].startswith("text/javascript"), (module, response.headers)


def test_every_page_runs_under_a_strict_csp(page):
    assert page.goto("/").headers["content-security-policy"] == STRICT_CSP
    pages = (("/#/", "#jobs tbody tr"), ("/#/new", "#upload"), ("/#/jobs/0123", "#error:not([hidden])"))
    for route, ready in pages:
        page.goto(route)
        page.wait_for_selector(ready)
    assert page.errors == []
    # and a violation would be seen: an inline style attribute is refused and reported
    with page.expect_console_message(lambda message: "Content Security Policy" in message.text):
        page.evaluate("document.body.setAttribute('style', 'color: red')")


def looking_at(image: str, centre: np.ndarray) -> dict:
    """A registered camera at `centre` looking at the origin, z up: world-to-camera R (OpenCV axes) and C."""
    forward = -centre / np.linalg.norm(centre)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    R = np.array([right, np.cross(forward, right), forward])
    return {"image": image, "R": R.tolist(), "t": (-R @ centre).tolist(), "C": centre.tolist()}


def opengl_c2w(camera: dict) -> np.ndarray:
    return np.c_[np.array(camera["R"]).T @ np.diag([1.0, -1.0, -1.0]), camera["C"]]


def test_the_novel_view_opens_at_a_registered_camera_and_follows_the_registered_cameras(page):
    """A NeRF job on a reconstruction of five photos on a 60-degree arc (the API answered here, each render a
    grey pixel): the view opens at the middle photo, a drag moves along the photos and stops at the last one,
    "free orbit" orbits the scene's centre from there, and unticking it returns to the photos."""
    angles = np.radians([-30, -15, 0, 15, 30])
    centres = [np.array([4 * np.sin(a), -4 * np.cos(a), 1.0]) for a in angles]
    cameras = [looking_at(f"{k:04d}.png", centre) for k, centre in enumerate(centres)]
    job = {"id": "n1", "kind": "nerf", "state": "succeeded", "stage": "done", "progress": 1.0, "error": None,
           "source_job_id": "r1", "created_at": "2026-11-28T00:00:00Z"}  # fmt: skip
    config = {"camera": {"width": 400, "height": 300}, "normalization": {"centre": [0, 0, 0], "scale": 1.0},
              "orbit": {"target": [0, 0, 0], "up": [0, 0, 1], "radius": 4.0}}  # fmt: skip
    grey_pixel = base64.b64decode(
        "iVBORw0KGgoAAAANSUhEUgAAAAEAAAABCAAAAAA6fptVAAAACklEQVR4nGNoAAAAggCBd81ytgAAAABJRU5ErkJggg=="
    )
    answers = {
        "/v1/jobs/n1": job,
        "/v1/jobs/n1/logs": {"lines": [], "next_offset": 0},
        "/v1/nerf/n1": {"job": job, "config": config, "metrics": []},
        "/v1/nerf/n1/checkpoints": [{"step": 10, "is_latest": True, "is_best": True, "val_psnr": None,
                                     "size_bytes": 1000, "url": "/v1/nerf/n1/checkpoints/10"}],  # fmt: skip
        "/v1/reconstructions/r1": {"cameras": cameras},
    }
    renders = []

    def fake_api(route) -> None:
        path = route.request.url.split("://", 1)[1].split("/", 1)[1].split("?")[0]
        if path == "v1/nerf/n1/render":
            renders.append(json.loads(route.request.post_data))
            route.fulfill(status=200, content_type="image/png", body=grey_pixel)
        elif f"/{path}" in answers:
            route.fulfill(status=200, json=answers[f"/{path}"])
        else:
            route.fulfill(status=404, json={"detail": f"{path} not found"})

    page.route(re.compile(r"/v1/"), fake_api)
    page.goto("/#/jobs/n1")
    novel = page.wait_for_selector("#novel-n1[data-renders='1']")
    label = "#novel-label-n1"
    assert novel.get_attribute("data-mode") == "path" and not page.is_checked("#free-n1")
    np.testing.assert_allclose(renders[0]["c2w"][:3], opengl_c2w(cameras[2]), atol=1e-9)
    assert page.inner_text(label) == "near photo 0002.png (3 of 5 along the path of registered cameras)"
    at_first_photo = "near photo 0000.png (1 of 5 along the path of registered cameras)"

    novel.scroll_into_view_if_needed()
    box = novel.bounding_box()
    page.mouse.move(box["x"] + 10, box["y"] + box["height"] / 2)
    page.mouse.down()
    page.mouse.move(box["x"] + 10 + 2 * box["width"], box["y"] + box["height"] / 2, steps=8)  # far right
    page.mouse.up()
    page.wait_for_selector(f"{label}:text-is('{at_first_photo}')")
    np.testing.assert_allclose(renders[-1]["c2w"][:3], opengl_c2w(cameras[0]), atol=1e-9)

    page.check("#free-n1")
    page.wait_for_selector(f"{label}:text-matches('^free orbit: azimuth -?\\\\d+°, elevation 14°$')")
    assert novel.get_attribute("data-mode") == "free"
    np.testing.assert_allclose(renders[-1]["eye"], cameras[0]["C"], atol=1e-9)
    assert renders[-1]["look_at"] == [0, 0, 0] and renders[-1]["up"] == [0, 0, 1]

    page.uncheck("#free-n1")
    page.wait_for_selector(f"{label}:text-is('{at_first_photo}')")
    np.testing.assert_allclose(renders[-1]["c2w"][:3], opengl_c2w(cameras[0]), atol=1e-9)
    assert page.errors == []
