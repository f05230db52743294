"""What the routers share: documented error answers, page sizes and the 202 Accepted answer."""

from __future__ import annotations

from fastapi import Response, UploadFile, status

from service.actions.reconstructions import InputFile
from service.schemas import ErrorOut, JobOut

NOT_FOUND = {404: {"model": ErrorOut, "description": "No job with this id."}}
#: Answers of every route that starts new work (service.deps.require_disk_space, the upload checks).
NEW_WORK_REFUSED = {
    429: {
        "model": ErrorOut,
        "description": "The client has its most jobs waiting, or every upload check is busy: send it again "
        "after Retry-After seconds.",
        "headers": {"Retry-After": {"description": "Seconds to wait.", "schema": {"type": "integer"}}},
    },
    507: {"model": ErrorOut, "description": "The server's disk, or the client's disk quota, is full."},
}
REJECTED = {
    413: {"model": ErrorOut, "description": "A limit was exceeded (named in the message)."},
    422: {"description": "Bad input; the message names the field and file."},
}
MAX_PAGE = 500


def accepted(response: Response, job: JobOut) -> JobOut:
    """202 Accepted with the job resource and its Location."""
    response.status_code = status.HTTP_202_ACCEPTED
    response.headers["Location"] = job.links["self"]
    return job


def input_file(upload: UploadFile | None) -> InputFile | None:
    """A request's file as the actions take it."""
    return None if upload is None else InputFile(upload.filename, upload.file, upload.content_type)


def input_files(uploads: list[UploadFile] | None) -> list[InputFile]:
    return [InputFile(upload.filename, upload.file, upload.content_type) for upload in uploads or []]
