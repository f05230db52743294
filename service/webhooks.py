"""Webhooks: POST a finished job's resource to the URL given with it, retried with exponential back-off."""

from __future__ import annotations

import logging
import threading
import time

import httpx

from service.db import Job, JobStore
from service.models import JobOut
from service.settings import ServiceSettings

log = logging.getLogger(__name__)
TIMEOUT_SECONDS = 10.0


def deliver(url: str, payload: str, attempts: int, backoff_seconds: float) -> bool:
    """POSTs payload (JSON) until a 2xx answer or `attempts` tries, waiting backoff, 2 backoff, ..."""
    delay = backoff_seconds
    for attempt in range(1, attempts + 1):
        try:
            response = httpx.post(
                url, content=payload, headers={"Content-Type": "application/json"}, timeout=TIMEOUT_SECONDS
            )
            if response.is_success:
                return True
            reason = f"HTTP {response.status_code}"
        except httpx.HTTPError as error:
            reason = f"{type(error).__name__}: {error}"
        log.warning("webhook %s attempt %d/%d failed: %s", url, attempt, attempts, reason)
        if attempt < attempts:
            time.sleep(delay)
            delay *= 2
    return False


def notify(store: JobStore, job_id: str, settings: ServiceSettings, *, background: bool) -> None:
    """Calls the job's webhook (if any) with its current resource; in a daemon thread when `background`."""
    job: Job | None = store.get(job_id)
    if job is None or not job.webhook_url:
        return
    payload = JobOut.from_job(job).model_dump_json()

    def send() -> None:
        delivered = deliver(
            job.webhook_url, payload, settings.webhook_attempts, settings.webhook_backoff_seconds
        )
        note = "delivered" if delivered else f"not delivered after {settings.webhook_attempts} attempts"
        store.append_log(job_id, [f"webhook {job.webhook_url}: {note}"])

    if background:
        threading.Thread(target=send, name=f"webhook-{job_id}", daemon=True).start()
    else:
        send()
