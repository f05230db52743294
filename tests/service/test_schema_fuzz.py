"""Schema fuzzing with schemathesis: every operation of the OpenAPI spec with generated requests, then
stateful sequences along the schema's links (create -> get -> cancel -> retry -> pin -> delete); no 5xx.

Each sequence starts from the same database: jobs of every kind in every finished state, so the links
have real ids to follow from the first step (`GET /v1/jobs`). Generated uploads are rejected before a
job exists; retries of the seeded jobs are real jobs (without inputs, they fail in their worker process).
"""

from __future__ import annotations

import atexit
import shutil
import tempfile
import time
from pathlib import Path

import pytest
import schemathesis
from hypothesis import HealthCheck, Phase, settings
from hypothesis.errors import FlakyStrategyDefinition
from sqlalchemy import delete

from service.app import create_app
from service.kinds import JobKind, JobState
from service.store import Job, JobStore, Scene
from tests.service.conftest import make_settings

EXAMPLES_PER_OPERATION = 100
STATEFUL_SEQUENCES = 50
STATEFUL_RUNS = 3
"""Runs of the state machine at most. The jobs it retries run for real, so a step's answer (409 or 2xx) can
depend on how far such a job got; hypothesis then refuses the run when a sequence's generation differs from
an earlier one's with the same start (FlakyStrategyDefinition: the generator's, not a server error). A fresh
run is as good a search; a server error fails at once."""
SETTLE_SECONDS = 60.0
"""Longest wait for the jobs of the previous sequence to end before the next one starts."""
# Generation only: no example database and no shrinking replays (the generators learn from the
# server's answers, which hypothesis would see as flaky data), so a failure is reported as found.
FUZZ = {
    "deadline": None,
    "database": None,
    "phases": [Phase.explicit, Phase.generate],
    "suppress_health_check": list(HealthCheck),
}

_data_dir = Path(tempfile.mkdtemp(prefix="sfmnerf-fuzz-"))
atexit.register(shutil.rmtree, _data_dir, True)
# A limit small enough that generated uploads hit it too.
_settings = make_settings(_data_dir / "data", max_upload_bytes=2_000_000, cancel_grace_seconds=0.0)


def seed(store: JobStore) -> None:
    """Only finished jobs of each kind and state, with fixed ids, and no scene: every sequence starts from
    this state."""
    with store.engine.begin() as connection:
        connection.execute(delete(Scene))
        connection.execute(delete(Job))
    for kind in JobKind:
        for state in (JobState.succeeded, JobState.failed, JobState.cancelled):
            job = store.create(kind, {}, job_id=f"seed{kind}{state}")
            attempt = store.claim(job.id, "seed")
            store.finish(job.id, attempt, state, error=None if state == JobState.succeeded else "seeded")


_store = JobStore(_settings.resolved_database_url)
seed(_store)
app = create_app(_settings)
schema = schemathesis.openapi.from_asgi("/openapi.json", app)


def assert_no_server_error(response, case) -> None:
    assert response.status_code < 500, (
        f"{case.method} {case.formatted_path}: {response.status_code} {response.text[:500]}"
    )


@pytest.mark.slow
@schema.parametrize()
@settings(max_examples=EXAMPLES_PER_OPERATION, **FUZZ)
def test_no_generated_request_gets_a_server_error(case):
    assert_no_server_error(case.call(), case)


def settle(store: JobStore) -> None:
    """Cancels the jobs that a sequence left queued or running and waits until they have ended: a job
    process still running holds the executor's slot, and the next sequence's answers would depend on it."""
    deadline = time.monotonic() + SETTLE_SECONDS
    while active := [*store.queued_ids(1000), *(job.id for job in store.running())]:
        assert time.monotonic() < deadline, f"still queued or running after {SETTLE_SECONDS:g} s: {active}"
        for job_id in active:
            store.request_cancel(job_id)
        time.sleep(0.05)


class JobWorkflow(schema.as_state_machine()):
    def setup(self) -> None:
        settle(_store)
        seed(_store)  # the same starting state for every sequence (what hypothesis replays must see)

    def validate_response(self, response, case, **kwargs) -> None:
        assert_no_server_error(response, case)


@pytest.mark.slow
def test_no_sequence_of_linked_calls_gets_a_server_error():
    for run in range(1, STATEFUL_RUNS + 1):
        try:
            JobWorkflow.run(settings=settings(max_examples=STATEFUL_SEQUENCES, stateful_step_count=6, **FUZZ))
            return
        except FlakyStrategyDefinition:
            if run == STATEFUL_RUNS:
                raise


# ---- hostile values in every field ----------------------------------------------------------------------

NON_FINITE = ["NaN", "Infinity", "-Infinity", "1e999"]
DEEP_ARRAY = "[" * 9000 + "]" * 9000
HOSTILE_JSON = [*NON_FINITE, DEEP_ARRAY, '{"a": NaN}', '{"a":' * 3000 + "1" + "}" * 3000]
SEEDED_KIND = {
    "/v1/nerf/": JobKind.nerf,
    "/v1/reconstructions/": JobKind.reconstruction,
    "/v1/jobs/": JobKind.nerf,
}
JSON_HEADERS = {"content-type": "application/json"}


def _resolve(spec: dict, schema: dict) -> dict:
    while "$ref" in schema:
        schema = spec["components"]["schemas"][schema["$ref"].rsplit("/", 1)[-1]]
    return schema


def _is_file(schema: dict) -> bool:
    items = schema.get("items", {})
    options = schema.get("anyOf", [])
    variants = [schema, items, *options, *[v.get("items", {}) for v in options]]
    return any(v.get("format") == "binary" or v.get("contentMediaType") for v in variants)


def _seeded_path(path: str) -> str:
    """The path with its ids filled by a seeded job (so a handler's 404 does not hide a body check)."""
    kind = next((k for prefix, k in SEEDED_KIND.items() if path.startswith(prefix)), JobKind.nerf)
    return path.replace("{job_id}", f"seed{kind}{JobState.succeeded}").replace("{scene_id}", "0" * 32)


def hostile_requests() -> list[tuple[str, str, dict]]:
    """(method, path, httpx arguments): NaN, Infinity, 1e999 and 9000-deep nesting in every field of
    every JSON body and every form field of every operation, the other fields left out."""
    spec = app.openapi()
    requests = []
    for path, operations in spec["paths"].items():
        for method, operation in operations.items():
            content = operation.get("requestBody", {}).get("content", {})
            url = _seeded_path(path)
            if "application/json" in content:
                body = _resolve(spec, content["application/json"]["schema"])
                requests.append((method, url, {"content": DEEP_ARRAY, "headers": JSON_HEADERS}))
                requests += [
                    (method, url, {"content": f'{{"{field}": {value}}}', "headers": JSON_HEADERS})
                    for field in body.get("properties", {})
                    for value in HOSTILE_JSON
                ]
            if "multipart/form-data" in content:
                form = _resolve(spec, content["multipart/form-data"]["schema"])["properties"]
                files = [(name, ("1.png", b"x", "image/png")) for name, f in form.items() if _is_file(f)]
                requests += [
                    (method, url, {"data": {name: value}, "files": files})
                    for name, field in form.items()
                    if not _is_file(field)
                    for value in HOSTILE_JSON
                ]
    return requests


@pytest.mark.slow
def test_nan_infinity_and_deep_nesting_in_every_field_answer_4xx():
    from fastapi.testclient import TestClient

    seed(_store)
    requests = hostile_requests()
    assert len(requests) > 100
    with TestClient(app) as client:
        for method, url, arguments in requests:
            response = client.request(method.upper(), url, **arguments)
            shown = {k: str(v)[:80] for k, v in arguments.items()}
            answer = f"{response.status_code} {response.text[:300]}"
            assert 400 <= response.status_code < 500, f"{method} {url} {shown}: {answer}"
