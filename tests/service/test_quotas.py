"""Per-client quotas on waiting jobs and disk, and a queue that serves clients in turns."""

from __future__ import annotations

import hashlib
from datetime import timedelta

import pytest
from fastapi.testclient import TestClient

from service.app import create_app
from service.auth import Client
from service.errors import ServiceError
from service.fair_queue import fair_order
from service.kinds import JobKind, JobState
from service.layout import job_dir
from service.quotas import check_client_quota
from service.store import JobStore, utcnow
from tests.service.conftest import make_settings

ALICE, BOB = Client("alice", False), Client("bob", False)


def test_the_queue_serves_clients_in_turns_whatever_their_backlog():
    queued = [(f"a{i}", "alice") for i in range(200)] + [("b0", "bob"), ("b1", "bob"), ("c0", None)]
    assert fair_order(queued, {})[:6] == ["a0", "b0", "c0", "a1", "b1", "a2"]


def test_a_client_with_fewer_running_jobs_goes_first():
    queued = [("a0", "alice"), ("b0", "bob")]
    assert fair_order(queued, {"alice": 2})[0] == "b0"


def test_the_store_claims_another_clients_job_before_a_backlog(tmp_path):
    store = JobStore(make_settings(tmp_path / "data").resolved_database_url)
    backlog = [store.create(JobKind.reconstruction, {}, owner="alice").id for _ in range(5)]
    other = store.create(JobKind.reconstruction, {}, owner="bob").id
    claimed = [job_id for job_id, _ in store.claim_next(2, "test", "supervisor")]
    assert claimed == [backlog[0], other]
    store.dispose()


def test_a_client_at_its_waiting_jobs_limit_gets_429_with_retry_after(tmp_path):
    settings = make_settings(tmp_path / "data", max_queued_jobs_per_client=2)
    store = JobStore(settings.resolved_database_url)
    for _ in range(2):
        store.create(JobKind.reconstruction, {}, owner="alice")
    with pytest.raises(ServiceError) as refused:
        check_client_quota(store, ALICE, settings)
    assert refused.value.status_code == 429 and int(refused.value.headers["Retry-After"]) > 0
    assert "SFMNERF_MAX_QUEUED_JOBS_PER_CLIENT=2" in refused.value.detail
    check_client_quota(store, BOB, settings)  # another client is not held by alice's backlog
    check_client_quota(store, Client("admin", True), settings)
    store.dispose()


def test_a_client_over_its_disk_quota_gets_507_naming_it(tmp_path):
    token = "alice-token-0123456789"
    clients = tmp_path / "clients.txt"
    clients.write_text(f"alice:sha256:{hashlib.sha256(token.encode()).hexdigest()}\n")
    settings = make_settings(tmp_path / "data", clients_file=clients, max_disk_bytes_per_client=1000)
    store = JobStore(settings.resolved_database_url)
    job = store.create(JobKind.reconstruction, {}, owner="alice")
    store.finish(job.id, store.claim(job.id, "test"), JobState.succeeded)
    (job_dir(settings, job.id) / "output").mkdir(parents=True)
    (job_dir(settings, job.id) / "output" / "points.ply").write_bytes(bytes(2000))
    store.dispose()
    with TestClient(create_app(settings)) as client:
        files = [("images", (f"{i}.png", b"x", "image/png")) for i in (1, 2)]
        auth = {"Authorization": f"Bearer {token}"}
        response = client.post("/v1/reconstructions", files=files, headers=auth)
        assert response.status_code == 507
        assert "SFMNERF_MAX_DISK_BYTES_PER_CLIENT=1000" in response.json()["detail"]


def test_webhooks_are_claimed_in_turns_and_one_client_never_holds_every_sender(tmp_path):
    """8 webhooks of alice due before bob's: bob's is the second claimed; alice never has more than 2
    deliveries under way."""
    store = JobStore(make_settings(tmp_path / "data").resolved_database_url)

    def finished_with_webhook(owner: str) -> str:
        job = store.create(JobKind.reconstruction, {}, owner=owner, webhook_url="http://example.org/hook")
        store.finish(job.id, store.claim(job.id, "test"), JobState.succeeded)
        store.queue_webhook(job.id)
        return job.id

    alices = [finished_with_webhook("alice") for _ in range(8)]
    bobs = finished_with_webhook("bob")
    stale_before = utcnow() - timedelta(minutes=5)
    claims = [store.claim_webhook(stale_before, per_owner=2) for _ in range(4)]
    assert [job.id if job else None for job in claims] == [alices[0], bobs, alices[1], None]
    store.dispose()


def test_every_route_that_starts_work_documents_429_with_retry_after_and_507(tmp_path):
    """Every operation answering 202 (it queues a job, behind the quota check) lists both refusals."""
    schema = create_app(make_settings(tmp_path / "data")).openapi()
    starting = [
        (path, method, operation["responses"])
        for path, operations in schema["paths"].items()
        for method, operation in operations.items()
        if "202" in operation["responses"]
    ]
    assert len(starting) >= 5, [path for path, _, _ in starting]
    for path, method, answers in starting:
        assert {"429", "507"} <= answers.keys(), (path, method)
        assert "Retry-After" in answers["429"]["headers"], (path, method)
