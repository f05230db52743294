"""OpenAPI details that generated clients depend on: operation ids and the description of file responses.

`openapi-python-client` turns each operation id into a function name and each response's media type into
a return type; `CLIENT_CONFIG` maps the image and video types it does not know to bytes.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from fastapi import FastAPI
from fastapi.routing import APIRoute

CLIENT_CONFIG = Path(__file__).with_name("openapi_client.yaml")
"""The generator's configuration: `openapi-python-client generate --config service/openapi_client.yaml`."""
BINARY_SCHEMA = {"type": "string", "format": "binary"}


def operation_id(route: APIRoute) -> str:
    """The route function's name (get_job, create_reconstruction, ...), unique across the API."""
    return route.name


def file_response(*media_types: str, description: str) -> dict[int | str, dict[str, Any]]:
    """The 200 response of a route that sends a file of one of these media types."""
    return {
        200: {
            "description": description,
            "content": {media: {"schema": BINARY_SCHEMA} for media in media_types},
        }
    }


def binary_as_format(schema: Any) -> Any:
    """The schema with file fields as `format: binary` (OpenAPI 3.0 style) besides 3.1's contentMediaType.

    FastAPI describes an UploadFile with `contentMediaType` only; generators (openapi-python-client among
    them) recognise a file by `format: binary` and would otherwise send uploads as strings.
    """
    if isinstance(schema, dict):
        fixed = {key: binary_as_format(value) for key, value in schema.items()}
        if fixed.get("type") == "string" and fixed.get("contentMediaType") == "application/octet-stream":
            fixed["format"] = "binary"
        return fixed
    if isinstance(schema, list):
        return [binary_as_format(item) for item in schema]
    return schema


JOB_OPERATIONS = {
    "GetJob": ("get", "/v1/jobs/{job_id}"),
    "GetLogs": ("get", "/v1/jobs/{job_id}/logs"),
    "CancelJob": ("post", "/v1/jobs/{job_id}/cancel"),
    "RetryJob": ("post", "/v1/jobs/{job_id}/retry"),
    "PinJob": ("put", "/v1/jobs/{job_id}/pin"),
    "UnpinJob": ("delete", "/v1/jobs/{job_id}/pin"),
    "DeleteJob": ("delete", "/v1/jobs/{job_id}"),
}
"""What a client can do with a job id an answer gave it (OpenAPI links, followed by clients and fuzzers)."""
JOB_ID_SOURCES = {
    ("post", "/v1/reconstructions", "202"): "$response.body#/id",
    ("post", "/v1/nerf", "202"): "$response.body#/id",
    ("post", "/v1/nerf/{job_id}/video", "202"): "$response.body#/id",
    ("post", "/v1/jobs/{job_id}/retry", "202"): "$response.body#/id",
    ("post", "/v1/jobs/{job_id}/cancel", "200"): "$response.body#/id",
    ("get", "/v1/jobs/{job_id}", "200"): "$response.body#/id",
    ("put", "/v1/jobs/{job_id}/pin", "200"): "$response.body#/id",
    ("get", "/v1/jobs", "200"): "$response.body#/items/0/id",
}


def add_job_links(schema: dict[str, Any]) -> dict[str, Any]:
    """Adds OpenAPI links from every answer that names a job to the operations on that job."""
    paths = schema["paths"]
    for (method, path, code), source in JOB_ID_SOURCES.items():
        response = paths[path][method]["responses"][code]
        response["links"] = {
            name: {"operationId": paths[target][verb]["operationId"], "parameters": {"job_id": source}}
            for name, (verb, target) in JOB_OPERATIONS.items()
        }
    return schema


def install(app: FastAPI) -> None:
    """Replaces app.openapi with one whose file fields say `format: binary` and whose answers that name a
    job link to the operations on it (computed once, cached)."""
    build = app.openapi

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is None:
            app.openapi_schema = binary_as_format(add_job_links(build()))
        return app.openapi_schema

    app.openapi = openapi  # type: ignore[method-assign]
