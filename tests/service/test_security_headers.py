"""The web app's browser protections (CSP on its own assets, nosniff, no framing, no referrer) and the
Host names the service answers to (DNS rebinding)."""

from __future__ import annotations

import re

import pytest
from fastapi.testclient import TestClient

from service.app import create_app
from service.routes.web import INDEX_PAGE
from service.security_headers import host_allowed, host_name
from service.settings import ServiceSettings
from tests.service.conftest import make_settings

TOKEN = "admin-token-0123456789"


def policy_of(response) -> dict[str, list[str]]:
    directives = [d.strip().split() for d in response.headers["Content-Security-Policy"].split(";")]
    return {d[0]: d[1:] for d in directives if d}


@pytest.mark.parametrize("path", ["/", "/static/app.js", "/static/style.css", "/v1/info", "/healthz"])
def test_every_answer_carries_the_browser_protections(client, path):
    response = client.get(path)
    assert response.status_code == 200
    assert response.headers["X-Content-Type-Options"] == "nosniff"
    assert response.headers["X-Frame-Options"] == "DENY"
    assert response.headers["Referrer-Policy"] == "no-referrer"
    assert policy_of(response)["frame-ancestors"] == ["'none'"]


def test_the_pages_policy_allows_its_own_assets_and_object_url_images_only(client):
    policy = policy_of(client.get("/"))
    assert policy == {
        "default-src": ["'self'"], "script-src": ["'self'"], "style-src": ["'self'"],
        "img-src": ["'self'", "blob:"], "connect-src": ["'self'"], "object-src": ["'none'"],
        "base-uri": ["'none'"], "form-action": ["'self'"], "frame-ancestors": ["'none'"],
    }  # fmt: skip


def test_the_page_has_no_inline_script_or_style_that_its_policy_would_block():
    page = INDEX_PAGE.read_text()
    assert not re.findall(r"<script(?![^>]*\bsrc=)[^>]*>", page), "every script is a file of the app"
    assert "<style" not in page and " style=" not in page


def test_the_docs_keep_their_cdn_viewer_but_cannot_be_framed(client):
    policy = policy_of(client.get("/docs"))
    assert policy == {"frame-ancestors": ["'none'"]}


# ---- trusted hosts ------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("header", "name"), [("localhost:8000", "localhost"), ("[::1]:8000", "::1"), ("::1", "::1"),
                         ("Example.ORG", "example.org"), ("127.0.0.1", "127.0.0.1")],
)
def test_the_host_name_is_read_without_its_port(header, name):
    assert host_name(header) == name


def test_host_patterns_match_names_and_subdomains():
    assert host_allowed("app.localhost", ["*.localhost"]) and not host_allowed("localhost", ["*.localhost"])
    assert not host_allowed("evil-localhost", ["*.localhost"]) and host_allowed("any.where", ["*"])


@pytest.mark.parametrize("host", ["evil.example", "localhost.evil.example", "10.0.0.7"])
def test_an_open_service_answers_only_to_localhost_names(tmp_path, host):
    """No token: the default trusted hosts are this machine's names; a rebound DNS name gets 400."""
    settings = ServiceSettings(data_dir=tmp_path / "data")
    with TestClient(create_app(settings), base_url="http://localhost:8000") as client:
        assert client.get("/v1/info").status_code == 200
        assert client.get("/", headers={"Host": "127.0.0.1:8000"}).status_code == 200
        refused = client.get("/v1/info", headers={"Host": host})
        assert refused.status_code == 400 and "SFMNERF_TRUSTED_HOSTS" in refused.json()["detail"]
        assert client.get("/healthz", headers={"Host": host}).status_code == 200  # probes by address


def test_a_service_behind_a_token_answers_any_host_unless_the_setting_narrows_it(tmp_path):
    auth = {"Authorization": f"Bearer {TOKEN}"}
    with TestClient(create_app(ServiceSettings(data_dir=tmp_path / "a", api_token=TOKEN))) as client:
        assert client.get("/v1/info", headers={**auth, "Host": "api.example.org"}).status_code == 200
    settings = make_settings(tmp_path / "b", api_token=TOKEN, trusted_hosts=["api.example.org"])
    with TestClient(create_app(settings)) as client:
        assert client.get("/v1/info", headers={**auth, "Host": "api.example.org"}).status_code == 200
        assert client.get("/v1/info", headers={**auth, "Host": "localhost"}).status_code == 400
