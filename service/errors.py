"""Domain errors: what the service refuses and why, with the HTTP status the app's one handler answers.

Actions, uploads and checks raise them; routes never translate them (service.app maps every
`ServiceError` to `{"detail": ...}` with its status), and the scene supervisor records their detail as a
scene's failure reason.
"""

from __future__ import annotations


class ServiceError(Exception):
    """A refusal with its HTTP status (404 not found, 409 conflict, 413 over a limit, 422 bad input, 429 busy
    or over a quota, 507 no disk space) and the headers it needs (Retry-After)."""

    def __init__(self, status_code: int, detail: str, headers: dict[str, str] | None = None) -> None:
        super().__init__(detail)
        self.status_code = status_code
        self.detail = detail
        self.headers = headers


def not_found(detail: str) -> ServiceError:
    return ServiceError(404, detail)


def conflict(detail: str) -> ServiceError:
    return ServiceError(409, detail)


def no_space(detail: str) -> ServiceError:
    return ServiceError(507, detail)


def busy(detail: str, retry_after_seconds: int) -> ServiceError:
    """429 Too Many Requests, with the seconds after which to try again."""
    return ServiceError(429, detail, headers={"Retry-After": str(retry_after_seconds)})


def retry_after_seconds(error: ServiceError) -> float | None:
    """The seconds a `busy` refusal asks the caller to wait before trying again; None for any other."""
    if error.status_code != 429 or not error.headers or "Retry-After" not in error.headers:
        return None
    return float(error.headers["Retry-After"])
