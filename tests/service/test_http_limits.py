"""Request bodies are bounded by the route they go to, never by the Content-Type the client chose;
JSON bodies hold finite numbers only and a bounded nesting."""

from __future__ import annotations

import asyncio
import contextlib
import json

import numpy as np
import pytest

from service.app import create_app
from service.http_limits import BodyKind, body_kind, flat_routes
from service.strict_json import MAX_JSON_DEPTH, JsonRefused, loads, nesting_depth
from tests.service.conftest import make_settings

UNKNOWN_ID = "0" * 32
MIB = 2**20


def asgi_post(
    app, path: str, headers: dict[str, str], chunks: int, chunk_bytes: int = MIB
) -> tuple[int, int]:
    """POSTs `chunks` chunks of a body straight through the ASGI app; (status, chunks the app received)."""
    scope = {
        "type": "http",
        "http_version": "1.1",
        "method": "POST",
        "scheme": "http",
        "path": path,
        "raw_path": path.encode(),
        "query_string": b"",
        "root_path": "",
        "headers": [(b"host", b"localhost")] + [(k.lower().encode(), v.encode()) for k, v in headers.items()],
        "client": ("127.0.0.1", 1),
        "server": ("127.0.0.1", 80),
    }
    received, sent = [], []

    async def receive():
        received.append(True)
        if len(received) > chunks:
            return {"type": "http.disconnect"}
        return {"type": "http.request", "body": b"x" * chunk_bytes, "more_body": len(received) < chunks}

    async def send(message):
        sent.append(message)

    async def run():
        # An exception after the answer (the app re-raises what it could not handle) does not matter here.
        with contextlib.suppress(Exception):
            await app(scope, receive, send)

    asyncio.run(run())
    return sent[0]["status"], len(received)


@pytest.fixture
def app(tmp_path):
    return create_app(make_settings(tmp_path / "data"))


def test_a_huge_body_labelled_multipart_to_a_json_route_is_refused_before_it_is_read(app):
    """500 MB declared as a multipart form to the render route: 413 at the JSON limit, nothing received."""
    headers = {"Content-Type": "multipart/form-data; boundary=x", "Content-Length": str(500 * MIB)}
    assert asgi_post(app, f"/v1/nerf/{UNKNOWN_ID}/render", headers, chunks=500) == (413, 0)


def test_a_huge_json_body_declared_is_refused_before_it_is_read(app):
    headers = {"Content-Type": "application/json", "Content-Length": str(500 * MIB)}
    assert asgi_post(app, f"/v1/nerf/{UNKNOWN_ID}/video", headers, chunks=500) == (413, 0)


@pytest.mark.parametrize(
    "content_type", ["application/json", "text/plain", "application/x-www-form-urlencoded"]
)
def test_a_streamed_body_to_a_json_route_stops_at_the_json_limit_whatever_its_label(app, content_type):
    """Chunked (no Content-Length): counted while it arrives; 1 MiB limit -> at most 2 chunks of 1 MiB."""
    status, received = asgi_post(app, f"/v1/nerf/{UNKNOWN_ID}/render", {"Content-Type": content_type}, 500)
    assert status == 413 and received <= 2


@pytest.mark.parametrize("path", [f"/v1/nerf/{UNKNOWN_ID}/render", f"/v1/jobs/{UNKNOWN_ID}/cancel"])
def test_a_streamed_multipart_body_to_a_route_without_a_form_is_refused_unread(app, path):
    """Multipart only where the route takes files: elsewhere 415 before the first byte is read."""
    headers = {"Content-Type": "multipart/form-data; boundary=x"}
    assert asgi_post(app, path, headers, chunks=500) == (415, 0)


def test_an_upload_route_still_takes_bodies_up_to_the_upload_limit(app):
    """3 MiB declared to /v1/reconstructions passes the limit and reaches the form parser (400: bad form)."""
    headers = {"Content-Type": "multipart/form-data; boundary=x", "Content-Length": str(3 * MIB)}
    status, received = asgi_post(app, "/v1/reconstructions", headers, chunks=3)
    assert status == 400 and received >= 1


def test_each_route_knows_the_body_it_takes(app):
    routes = [r for r in flat_routes(app.routes) if hasattr(r, "dependant")]
    kinds = {(method, r.path): body_kind(r) for r in routes for method in r.methods}
    assert kinds[("POST", "/v1/reconstructions")] == BodyKind.files
    assert kinds[("POST", "/v1/nerf")] == BodyKind.files
    assert kinds[("POST", "/v1/scenes")] == BodyKind.files
    assert kinds[("POST", "/v1/nerf/{job_id}/render")] == BodyKind.json
    assert kinds[("POST", "/v1/jobs/{job_id}/cancel")] == BodyKind.none


# ---- finite numbers and bounded nesting ---------------------------------------------------------------


@pytest.mark.parametrize(
    ("text", "words"),
    [
        ('{"c2w": [[1, 0, 0, NaN]]}', ["body.c2w[0][3]", "NaN"]),
        ('{"width": Infinity}', ["body.width", "Infinity"]),
        ('{"fx": -Infinity}', ["body.fx", "-Infinity"]),
        ('{"fx": 1e999}', ["body.fx", "1e999"]),
        ("[" * 9000 + "]" * 9000, ["body", f"deeper than {MAX_JSON_DEPTH}"]),
        ('{"a": ' * 9000 + "1" + "}" * 9000, ["body", f"deeper than {MAX_JSON_DEPTH}"]),
    ],
    ids=["nan", "infinity", "minus-infinity", "overflow", "deep-array", "deep-object"],
)
def test_non_finite_numbers_and_deep_nesting_are_refused_naming_the_element(text, words):
    with pytest.raises(JsonRefused) as refused:
        loads(text, "body")
    for word in words:
        assert word in str(refused.value)


def test_brackets_inside_strings_do_not_count_as_nesting():
    assert nesting_depth('{"a": "[[[[[[[[{{{{\\"[[["}') == 1
    assert loads('{"a": ["[[[[", 1.5, "NaN"]}', "body") == {"a": ["[[[[", 1.5, "NaN"]}


@pytest.mark.parametrize(
    ("body", "field"),
    [
        ('{"c2w": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, NaN], [0, 0, 0, 1]], "width": 8, "height": 8}',
         "body.c2w[2][3]"),
        ('{"eye": [0, 0, Infinity], "look_at": [0, 0, 0], "width": 8, "height": 8}', "body.eye[2]"),
        ('{"c2w": ' + "[" * 9000 + "]" * 9000 + ', "width": 8, "height": 8}', "body"),
    ],
    ids=["nan", "infinity", "deep"],
)
def test_a_render_request_with_nan_infinity_or_deep_nesting_answers_422_naming_the_field(client, body, field):
    response = client.post(
        f"/v1/nerf/{UNKNOWN_ID}/render", content=body, headers={"Content-Type": "application/json"}
    )
    assert response.status_code == 422, response.text
    assert response.json()["detail"].startswith(f"{field}:")


@pytest.mark.parametrize(
    ("options", "words"),
    [
        ('{"lr": NaN}', ["options.lr", "NaN"]),
        ('{"model_options": {"width": Infinity}}', ["options.model_options.width", "Infinity"]),
        ('{"a":' * 3000 + "1" + "}" * 3000, ["options", "deeper than"]),
        ("[" * 9000 + "]" * 9000, ["options", "deeper than"]),
    ],
    ids=["nan", "nested-infinity", "deep-object", "deep-array"],
)
@pytest.mark.parametrize("route", ["/v1/nerf", "/v1/scenes"])
def test_options_holding_nan_infinity_or_deep_nesting_answer_422_naming_them(client, route, options, words):
    npz = np.zeros(4, np.uint8).tobytes()
    files = {"dataset": ("d.npz", npz, "application/octet-stream")} if route == "/v1/nerf" else {
        "images": ("1.png", b"x", "image/png")
    }
    response = client.post(route, files=files, data={"options": options})
    assert response.status_code == 422, response.text
    detail = response.json()["detail"]
    for word in words:
        assert word in json.dumps(detail)
