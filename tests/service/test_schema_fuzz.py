"""Schema fuzzing with schemathesis: generated requests for every operation of the OpenAPI spec, no 5xx."""

from __future__ import annotations

import atexit
import shutil
import tempfile
from pathlib import Path

import schemathesis
from hypothesis import HealthCheck, settings

from service.app import create_app
from tests.service.conftest import make_settings

EXAMPLES_PER_OPERATION = 5

_data_dir = Path(tempfile.mkdtemp(prefix="sfmnerf-fuzz-"))
atexit.register(shutil.rmtree, _data_dir, True)
# A limit small enough that generated uploads hit it too; a request never starts a real job (every
# generated dataset or image set is rejected before a job exists).
app = create_app(make_settings(_data_dir / "data", max_upload_bytes=2_000_000))
schema = schemathesis.openapi.from_asgi("/openapi.json", app)


@schema.parametrize()
@settings(max_examples=EXAMPLES_PER_OPERATION, deadline=None, suppress_health_check=list(HealthCheck))
def test_no_generated_request_gets_a_server_error(case):
    response = case.call()
    assert response.status_code < 500, (
        f"{case.method} {case.formatted_path}: {response.status_code} {response.text[:500]}"
    )
