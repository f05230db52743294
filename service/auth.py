"""Who is calling: API tokens checked in ASGI middleware, before a request's body is read.

Two kinds of token: the admin token (`SFMNERF_API_TOKEN`, sees every job) and named client tokens from
`SFMNERF_CLIENTS_FILE` (`name:sha256:HEX` lines; a client sees only the jobs it created). Tokens are kept
as SHA-256 digests only and compared in constant time. With neither configured the service is open and
every caller is the anonymous admin.
"""

from __future__ import annotations

import hashlib
import hmac
import re
from dataclasses import dataclass
from pathlib import Path

from starlette.responses import JSONResponse
from starlette.types import ASGIApp, Receive, Scope, Send

from service.settings import ServiceSettings

ADMIN = "admin"
CLIENT_LINE = re.compile(r"^(?P<name>[A-Za-z0-9._-]{1,64}):sha256:(?P<digest>[0-9a-fA-F]{64})$")
PUBLIC_PATHS = frozenset({"/healthz", "/readyz"})
DOCS_PATHS = frozenset({"/docs", "/docs/oauth2-redirect", "/redoc", "/openapi.json"})
STATE_KEY = "client"


@dataclass(frozen=True)
class Client:
    """The caller of a request: its name (recorded as a job's owner) and whether it sees every job."""

    name: str | None
    admin: bool

    def may_see(self, owner: str | None) -> bool:
        return self.admin or (owner is not None and owner == self.name)


ANONYMOUS = Client(name=None, admin=True)


def token_digest(token: str) -> bytes:
    return hashlib.sha256(token.encode()).digest()


def read_clients_file(path: Path) -> dict[str, bytes]:
    """name -> SHA-256 digest of its token, from `name:sha256:HEX` lines (# comments and blanks skipped)."""
    clients: dict[str, bytes] = {}
    for number, raw in enumerate(path.read_text().splitlines(), start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        found = CLIENT_LINE.match(line)
        if not found:
            raise ValueError(f"{path}:{number}: expected 'name:sha256:<64 hex digits>'")
        name = found["name"]
        if name == ADMIN or name in clients:
            raise ValueError(f"{path}:{number}: the client name {name!r} is reserved or used twice")
        clients[name] = bytes.fromhex(found["digest"])
    return clients


class Authenticator:
    """Maps a bearer token to its Client; every known digest is compared, so timing tells nothing."""

    def __init__(self, settings: ServiceSettings) -> None:
        self._digests: list[tuple[bytes, Client]] = []
        if settings.api_token is not None:
            self._digests.append((token_digest(settings.api_token.get_secret_value()), Client(ADMIN, True)))
        if settings.clients_file is not None:
            for name, digest in read_clients_file(settings.clients_file).items():
                self._digests.append((digest, Client(name, False)))

    @property
    def enabled(self) -> bool:
        return bool(self._digests)

    def identify(self, token: str) -> Client | None:
        presented = token_digest(token)
        found = None
        for digest, client in self._digests:
            if hmac.compare_digest(presented, digest) and found is None:
                found = client
        return found


def bearer_token(scope: Scope) -> str | None:
    for key, value in scope["headers"]:
        if key == b"authorization":
            scheme, _, token = value.decode("latin-1").partition(" ")
            return token.strip() if scheme.lower() == "bearer" else None
    return None


class AuthMiddleware:
    """Answers 401 to a request without a valid token before anything reads its body; stores its Client."""

    def __init__(self, app: ASGIApp, settings: ServiceSettings) -> None:
        self.app = app
        self.authenticator = Authenticator(settings)
        self.public = PUBLIC_PATHS | (DOCS_PATHS if settings.docs == "public" else frozenset())

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        client: Client | None = ANONYMOUS
        if self.authenticator.enabled and scope["path"] not in self.public:
            token = bearer_token(scope)
            client = self.authenticator.identify(token) if token else None
            if client is None:
                response = JSONResponse(
                    {"detail": "missing or wrong API token (Authorization: Bearer TOKEN)"},
                    status_code=401,
                    headers={"WWW-Authenticate": "Bearer"},
                )
                await response(scope, receive, send)
                return
        scope.setdefault("state", {})[STATE_KEY] = client
        await self.app(scope, receive, send)
