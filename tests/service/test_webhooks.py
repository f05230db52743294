"""Webhooks are a persistent outbox: a job's end marks its webhook due, and the API's senders deliver it,
each one once, also when the service restarted in between or a sender died holding it."""

from __future__ import annotations

import time
from datetime import timedelta

import pytest
from fastapi.testclient import TestClient

from service.app import create_app
from service.job_end import complete_job
from service.kinds import JobKind, JobState
from service.store import JobStore, utcnow
from service.webhooks import WebhookSender, delivery_deadline_seconds
from tests.service.conftest import WebhookReceiver, make_settings

DELIVERY_WAIT_SECONDS = 15.0


@pytest.fixture
def receiver():
    receiver = WebhookReceiver()
    yield receiver
    receiver.close()


def finished_job(store: JobStore, settings, url: str, state: JobState = JobState.succeeded) -> str:
    """A job with a webhook, claimed and ended the one way jobs end (`complete_job`)."""
    job = store.create(JobKind.reconstruction, {}, webhook_url=url)
    attempt = store.claim(job.id, worker="test")
    assert complete_job(store, settings, job.id, attempt, state, error=None if state == "succeeded" else "x")
    return job.id


def wait_for(condition, seconds: float = DELIVERY_WAIT_SECONDS) -> None:
    deadline = time.monotonic() + seconds
    while not condition():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.05)


def test_a_webhook_due_while_no_service_ran_is_delivered_once_when_it_starts(tmp_path, receiver):
    settings = make_settings(tmp_path / "data", webhook_allowed_networks=["127.0.0.0/8"])
    store = JobStore(settings.resolved_database_url)
    job_id = finished_job(store, settings, receiver.url)  # e.g. by a job process, the API down
    assert store.get(job_id).webhook_state == "pending" and receiver.requests == []

    with TestClient(create_app(settings)):
        wait_for(lambda: store.get(job_id).webhook_state == "delivered")
        time.sleep(5 * settings.webhook_poll_seconds)  # the senders keep polling: nothing is sent twice
    assert [body["id"] for body in receiver.bodies()] == [job_id]
    assert receiver.bodies()[0]["state"] == "succeeded"
    assert store.read_logs(job_id, 0, 1000)[-1] == "webhook delivered"


def test_every_due_webhook_goes_exactly_once_with_two_senders_on_one_store(tmp_path, receiver):
    settings = make_settings(tmp_path, webhook_allowed_networks=["127.0.0.0/8"])
    store = JobStore(settings.resolved_database_url)
    job_ids = {finished_job(store, settings, receiver.url, state) for state in ("succeeded", "failed") * 3}
    senders = [WebhookSender(store, settings), WebhookSender(store, settings)]
    for sender in senders:
        sender.start()
    try:
        wait_for(lambda: len(receiver.requests) >= len(job_ids))
        time.sleep(5 * settings.webhook_poll_seconds)
    finally:
        for sender in senders:
            sender.stop()
    assert sorted(body["id"] for body in receiver.bodies()) == sorted(job_ids)


def test_a_claim_is_taken_over_only_once_its_sender_can_no_longer_be_sending(tmp_path):
    settings = make_settings(tmp_path)
    store = JobStore(settings.resolved_database_url)
    job_id = finished_job(store, settings, "http://127.0.0.1:9/never")
    fresh_cutoff = utcnow() - timedelta(seconds=delivery_deadline_seconds(settings))
    assert store.claim_webhook(fresh_cutoff).id == job_id  # one sender holds it now ...
    assert store.claim_webhook(fresh_cutoff) is None  # ... so another one may not take it
    # that sender died: once its claim is older than the longest delivery, another sender takes it over
    assert store.claim_webhook(utcnow() + timedelta(seconds=1)).id == job_id


def test_a_webhook_that_keeps_failing_is_recorded_failed_and_not_sent_again(tmp_path):
    failing = WebhookReceiver(status=500)
    settings = make_settings(tmp_path, webhook_allowed_networks=["127.0.0.0/8"])
    store = JobStore(settings.resolved_database_url)
    job_id = finished_job(store, settings, failing.url)
    sender = WebhookSender(store, settings)
    try:
        assert sender.send_one() and not sender.send_one()
    finally:
        failing.close()
    assert len(failing.requests) == settings.webhook_attempts
    assert store.get(job_id).webhook_state == "failed"
    assert store.read_logs(job_id, 0, 1000)[-1] == "webhook failed"


def test_a_job_without_a_webhook_url_never_becomes_due(tmp_path):
    settings = make_settings(tmp_path)
    store = JobStore(settings.resolved_database_url)
    job = store.create(JobKind.reconstruction, {})
    complete_job(store, settings, job.id, store.claim(job.id, worker="test"), JobState.succeeded)
    assert store.get(job.id).webhook_state is None
    assert store.claim_webhook(utcnow() + timedelta(hours=1)) is None
