"""Browser-facing protections: response headers for the web app, and the Host names the service answers.

`SecurityHeaders` gives every response `X-Content-Type-Options: nosniff`, `X-Frame-Options: DENY`,
`Referrer-Policy: no-referrer` and a Content-Security-Policy that allows the app's own assets only (ES
modules and a style sheet from the service, no inline script or style, no eval), and images also from the
blob: URLs the app makes of API responses; /docs and /redoc load their viewers from a CDN, so they only get
`frame-ancestors 'none'`. `TrustedHosts` answers 400 to a Host header outside
SFMNERF_TRUSTED_HOSTS, so a page on another site cannot reach a local service through DNS rebinding.
"""

from __future__ import annotations

from starlette.datastructures import MutableHeaders
from starlette.responses import JSONResponse
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.auth import DOCS_PATHS
from service.settings import ServiceSettings

HEALTH_PATHS = frozenset({"/healthz", "/readyz"})
"""Probes (load balancers, orchestrators) call these by address; they hold no data."""


CONTENT_SECURITY_POLICY = "; ".join(
    f"{directive} {sources}"
    for directive, sources in {
        "default-src": "'self'",
        "script-src": "'self'",
        "style-src": "'self'",
        "img-src": "'self' blob:",  # renders, photos and videos are object URLs of API responses
        "connect-src": "'self'",
        "object-src": "'none'",
        "base-uri": "'none'",
        "form-action": "'self'",
        "frame-ancestors": "'none'",
    }.items()
)
"""The web app's policy: its own scripts, styles, API calls and (object-URL) images, nothing else."""


class SecurityHeaders:
    """Adds the browser protections above to every HTTP response."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        policy = "frame-ancestors 'none'" if scope["path"] in DOCS_PATHS else CONTENT_SECURITY_POLICY

        async def send_with_headers(message: Message) -> None:
            if message["type"] == "http.response.start":
                headers = MutableHeaders(scope=message)
                headers.setdefault("Content-Security-Policy", policy)
                headers.setdefault("X-Content-Type-Options", "nosniff")
                headers.setdefault("X-Frame-Options", "DENY")
                headers.setdefault("Referrer-Policy", "no-referrer")
            await send(message)

        await self.app(scope, receive, send_with_headers)


def host_name(host_header: str) -> str:
    """The name in a Host header, without its port: 'localhost:8000' -> 'localhost', '[::1]:80' -> '::1'."""
    host = host_header.strip().lower()
    if host.startswith("["):
        return host[1 : host.find("]")] if "]" in host else host
    return host.rsplit(":", 1)[0] if host.count(":") == 1 else host


def host_allowed(name: str, patterns: list[str]) -> bool:
    """Exact names, '*.example.org' for any subdomain, '*' for any host."""
    return any(
        pattern == "*" or name == pattern or (pattern.startswith("*.") and name.endswith(pattern[1:]))
        for pattern in patterns
    )


class TrustedHosts:
    """Answers 400 to a request whose Host header names no trusted host (see the module docstring)."""

    def __init__(self, app: ASGIApp, settings: ServiceSettings) -> None:
        self.app = app
        self.patterns = settings.effective_trusted_hosts()

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or "*" in self.patterns or scope["path"] in HEALTH_PATHS:
            await self.app(scope, receive, send)
            return
        host = next((value.decode("latin-1") for key, value in scope["headers"] if key == b"host"), "")
        if not host_allowed(host_name(host), self.patterns):
            response = JSONResponse(
                {"detail": "this Host header is not served (SFMNERF_TRUSTED_HOSTS)"}, status_code=400
            )
            await response(scope, receive, send)
            return
        await self.app(scope, receive, send)
