"""Request bodies bounded by what the route takes, never by what the request says it is.

A route that takes files may receive a multipart body up to SFMNERF_MAX_UPLOAD_BYTES; every other body
(JSON, or a form without files) is held to SFMNERF_MAX_JSON_BYTES, whatever its Content-Type. A body over
the limit is answered 413 before it is read when Content-Length declares it, and as soon as the streamed
bytes pass the limit otherwise (chunked transfer). Multipart is refused (415) where the route takes no
form at all. A JSON body is read whole (it is small) and checked by `service.strict_json` before the route
parses it: NaN, Infinity and deep nesting are answered 422 naming the field.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from enum import StrEnum

from fastapi import params
from fastapi.dependencies.models import Dependant
from fastapi.routing import APIRoute
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.responses import JSONResponse
from starlette.routing import BaseRoute, Match
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.settings import ServiceSettings
from service.strict_json import JsonRefused, loads

BODY_METHODS = frozenset({"POST", "PUT", "PATCH"})


class BodyKind(StrEnum):
    """What a route reads from a request body."""

    none = "none"
    json = "json"
    form = "form"
    files = "files"


def _body_params(dependant: Dependant) -> Iterator[object]:
    yield from (field.field_info for field in dependant.body_params)
    for dependency in dependant.dependencies:
        yield from _body_params(dependency)


def body_kind(route: APIRoute) -> BodyKind:
    infos = list(_body_params(route.dependant))
    if any(isinstance(info, params.File) for info in infos):
        return BodyKind.files
    if any(isinstance(info, params.Form) for info in infos):
        return BodyKind.form
    return BodyKind.json if infos else BodyKind.none


def flat_routes(routes: Iterable[BaseRoute]) -> Iterator[BaseRoute]:
    """The routes of an app with those of its included routers in place (their paths hold the prefix:
    the app includes its routers without one)."""
    for route in routes:
        included = getattr(route, "original_router", None)  # FastAPI's wrapper of an included router
        if included is not None:
            yield from flat_routes(included.routes)
        else:
            yield route


def _header(scope: Scope, name: bytes) -> bytes | None:
    for key, value in scope["headers"]:
        if key == name:
            return value
    return None


class BodyLimits:
    """The body limit of the route a request goes to (see the module docstring)."""

    def __init__(self, app: ASGIApp, settings: ServiceSettings) -> None:
        self.app = app
        self.settings = settings
        self._kinds: dict[int, BodyKind] = {}

    def route_kind(self, scope: Scope) -> BodyKind:
        """The body the matching route reads; `json` (the small limit) when no route matches."""
        for route in flat_routes(scope["app"].router.routes):
            match, _ = route.matches(scope)
            if match == Match.FULL:
                if not isinstance(route, APIRoute):
                    return BodyKind.none
                if id(route) not in self._kinds:
                    self._kinds[id(route)] = body_kind(route)
                return self._kinds[id(route)]
        return BodyKind.json

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        kind = self.route_kind(scope)
        content_type = (_header(scope, b"content-type") or b"").lower()
        multipart = content_type.startswith(b"multipart/")
        if kind == BodyKind.files and multipart:
            max_bytes, variable = self.settings.max_upload_bytes, "SFMNERF_MAX_UPLOAD_BYTES"
        else:
            max_bytes, variable = self.settings.max_json_bytes, "SFMNERF_MAX_JSON_BYTES"
        detail = f"the request body is larger than the limit {variable}={max_bytes}"
        declared = _header(scope, b"content-length")
        if declared is not None and declared.isdigit() and int(declared) > max_bytes:
            await JSONResponse({"detail": detail}, status_code=413)(scope, receive, send)
            return
        if multipart and kind in (BodyKind.json, BodyKind.none) and scope["method"] in BODY_METHODS:
            response = JSONResponse({"detail": "this route takes no multipart form"}, status_code=415)
            await response(scope, receive, send)
            return
        received = 0

        async def limited_receive() -> Message:
            nonlocal received
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > max_bytes:
                    # An HTTPException passes FastAPI's body parsing unchanged and becomes the response.
                    raise StarletteHTTPException(413, detail)
            return message

        if kind == BodyKind.json and not multipart and scope["method"] in BODY_METHODS:
            await self._checked_json(scope, receive, send, max_bytes, detail)
            return
        await self.app(scope, limited_receive, send)

    async def _checked_json(
        self, scope: Scope, receive: Receive, send: Send, max_bytes: int, detail: str
    ) -> None:
        """Reads the (small) JSON body, refuses NaN/Infinity/deep nesting, then hands it on unchanged."""
        chunks, size, more = [], 0, True
        while more:
            message = await receive()
            if message["type"] != "http.request":  # the client went away
                return
            chunks.append(message.get("body", b""))
            size += len(chunks[-1])
            if size > max_bytes:
                await JSONResponse({"detail": detail}, status_code=413)(scope, receive, send)
                return
            more = message.get("more_body", False)
        body = b"".join(chunks)
        if body.strip():
            try:
                loads(body, "body")
            except JsonRefused as refused:
                await JSONResponse({"detail": str(refused)}, status_code=422)(scope, receive, send)
                return
        replayed = False

        async def replay() -> Message:
            nonlocal replayed
            if not replayed:
                replayed = True
                return {"type": "http.request", "body": body, "more_body": False}
            return await receive()

        await self.app(scope, replay, send)
