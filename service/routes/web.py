"""The web app at `/`: a single page (service/web/: HTML, JS, CSS, vendored three.js) on the /v1 API.

The page and its assets need no token (they hold no data); the page sends the token it keeps in the
browser's localStorage with every API request.
"""

from __future__ import annotations

import mimetypes
from pathlib import Path

from fastapi import FastAPI
from fastapi.responses import FileResponse
from fastapi.staticfiles import StaticFiles

WEB_DIR = Path(__file__).resolve().parents[1] / "web"
INDEX_PAGE = WEB_DIR / "index.html"


def mount(app: FastAPI) -> None:
    """Serves index.html at `/` and the assets under `/static/`."""
    # The app is ES modules: browsers refuse a module script served as anything but JavaScript, and the
    # platform's MIME table (the Windows registry, a container without /etc/mime.types) may say otherwise.
    mimetypes.add_type("text/javascript", ".js")
    mimetypes.add_type("image/svg+xml", ".svg")
    app.mount("/static", StaticFiles(directory=WEB_DIR), name="static")

    @app.get("/", include_in_schema=False)
    def index() -> FileResponse:
        return FileResponse(INDEX_PAGE, media_type="text/html")
