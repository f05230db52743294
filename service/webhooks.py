"""Webhooks: POST a finished job's resource to the URL given with it, from a sender apart from the job.

A URL is checked when the job is submitted (`check_url`: 422 naming `webhook_url`) and again when it is
called: its host is resolved once, every address must be public (the `ipaddress` module classifies it,
whatever the spelling: 2130706433, 0x7f.1, ::ffff:127.0.0.1) unless SFMNERF_WEBHOOK_ALLOWED_NETWORKS holds
it, and the request goes to that checked address (the Host header and TLS name stay the URL's): a second
DNS answer cannot redirect it. Redirects are not followed, proxies from the environment are not used.

Deliveries are a persistent outbox in the job store: whichever process ends a job marks its webhook
pending (`JobStore.queue_webhook`, a job process too), and the `WebhookSender` threads of every API process
claim due ones and send them, in turns across clients and at most SENDER_THREADS_PER_OWNER of one client's
at once. A restart loses none (a pending one waits in the database), a claim whose
sender died is taken over after the longest a delivery can take, and a webhook that never answers holds
neither a request nor a job slot. The job's log says only "webhook delivered" or "webhook failed"; the
reasons go to the server log.
"""

from __future__ import annotations

import ipaddress
import logging
import socket
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import timedelta
from ipaddress import IPv4Address, IPv4Network, IPv6Address, IPv6Network

import httpx

from service.schemas import JobOut
from service.settings import ServiceSettings
from service.store.job_store import JobStore
from service.store.tables import utcnow
from service.uploads import invalid

log = logging.getLogger(__name__)
SENDER_THREADS = 4
SENDER_THREADS_PER_OWNER = 2
"""Deliveries of one client under way at once: its silent webhooks never hold every sender thread."""
CLAIM_MARGIN_SECONDS = 30.0

Network = IPv4Network | IPv6Network


class WebhookRefused(ValueError):
    """A webhook URL the service will not call; the message says why (without probing further)."""


@dataclass(frozen=True)
class Target:
    """A checked webhook: the URL to connect to (its host replaced by the checked address) and its host."""

    url: httpx.URL
    host: str


def _public_or_allowed(address: IPv4Address | IPv6Address, allowed: Sequence[Network]) -> bool:
    if isinstance(address, IPv6Address) and address.ipv4_mapped is not None:
        address = address.ipv4_mapped
    if any(address in network for network in allowed):
        return True
    return not (
        address.is_loopback
        or address.is_link_local
        or address.is_private
        or address.is_reserved
        or address.is_multicast
        or address.is_unspecified
        or not address.is_global
    )


def resolve(url: str, allowed: Sequence[Network]) -> Target:
    """The URL pinned to its host's first address, every address checked; WebhookRefused otherwise."""
    try:
        parsed = httpx.URL(url)
    except (httpx.InvalidURL, ValueError) as error:
        raise WebhookRefused(f"not a valid URL ({error})") from None
    if parsed.scheme not in ("http", "https") or not parsed.host:
        raise WebhookRefused("must be an http:// or https:// URL with a host")
    if parsed.userinfo:
        raise WebhookRefused("must not hold credentials (user:password@); put a secret in the path instead")
    port = parsed.port or (443 if parsed.scheme == "https" else 80)
    try:
        infos = socket.getaddrinfo(parsed.host, port, type=socket.SOCK_STREAM)
    except (socket.gaierror, UnicodeError):
        raise WebhookRefused(f"the host {parsed.host!r} cannot be resolved") from None
    addresses = [ipaddress.ip_address(info[4][0].split("%")[0]) for info in infos]
    if not addresses or not all(_public_or_allowed(address, allowed) for address in addresses):
        raise WebhookRefused(
            f"the host {parsed.host!r} is not a public address (loopback, private, link-local, reserved, "
            "multicast or unspecified); SFMNERF_WEBHOOK_ALLOWED_NETWORKS can permit it"
        )
    return Target(url=parsed.copy_with(host=str(addresses[0])), host=parsed.host)


def check_url(url: str | None, settings: ServiceSettings) -> str | None:
    """The webhook URL of a submission, checked (422 naming `webhook_url` when refused)."""
    if url is None:
        return None
    try:
        resolve(url, settings.webhook_allowed_networks)
    except WebhookRefused as refused:
        raise invalid(f"webhook_url: {refused}") from None
    return url


def deliver(url: str, payload: str, settings: ServiceSettings) -> bool:
    """POSTs payload (JSON) until a 2xx answer or SFMNERF_WEBHOOK_ATTEMPTS tries, with doubling back-off."""
    delay = settings.webhook_backoff_seconds
    for attempt in range(1, settings.webhook_attempts + 1):
        try:
            target = resolve(url, settings.webhook_allowed_networks)
            with httpx.Client(
                follow_redirects=False, trust_env=False, timeout=settings.webhook_timeout_seconds
            ) as client:
                response = client.post(
                    target.url,
                    content=payload,
                    headers={"Content-Type": "application/json", "Host": _host_header(url)},
                    extensions={"sni_hostname": target.host},
                )
            if response.is_success:
                return True
            reason = f"HTTP {response.status_code}"
        except WebhookRefused as refused:
            reason = str(refused)
        except httpx.HTTPError as error:
            reason = f"{type(error).__name__}: {error}"
        log.warning("webhook attempt %d/%d failed: %s", attempt, settings.webhook_attempts, reason)
        if attempt < settings.webhook_attempts:
            time.sleep(delay)
            delay *= 2
    return False


def _host_header(url: str) -> str:
    parsed = httpx.URL(url)
    return parsed.netloc.decode("ascii")


def delivery_deadline_seconds(settings: ServiceSettings) -> float:
    """The longest one `deliver` can take (every attempt timing out, every back-off slept), plus a margin:
    a claim older than this belongs to a sender that died."""
    backoff = settings.webhook_backoff_seconds * (2 ** (settings.webhook_attempts - 1) - 1)
    return settings.webhook_attempts * settings.webhook_timeout_seconds + backoff + CLAIM_MARGIN_SECONDS


class WebhookSender:
    """Sender threads of a long-lived process (the API): they claim due webhooks from the job store's
    outbox, POST each job's resource as it is now, and record the outcome in the job's log."""

    def __init__(self, store: JobStore, settings: ServiceSettings) -> None:
        self.store, self.settings = store, settings
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []

    def start(self) -> None:
        for index in range(SENDER_THREADS):
            thread = threading.Thread(target=self._send_due, name=f"webhook-{index}", daemon=True)
            thread.start()
            self._threads.append(thread)

    def stop(self) -> None:
        """Stops claiming; a delivery under way is left to finish (its claim goes stale if it cannot)."""
        self._stop.set()

    def send_one(self) -> bool:
        """Claims and sends one due webhook; False when none is due."""
        stale_before = utcnow() - timedelta(seconds=delivery_deadline_seconds(self.settings))
        job = self.store.claim_webhook(stale_before, per_owner=SENDER_THREADS_PER_OWNER)
        if job is None:
            return False
        delivered = deliver(job.webhook_url or "", JobOut.from_job(job).model_dump_json(), self.settings)
        self.store.finish_webhook(job.id, delivered)
        self.store.append_log(job.id, ["webhook delivered" if delivered else "webhook failed"])
        return True

    def _send_due(self) -> None:
        while not self._stop.is_set():
            try:
                if self.send_one():
                    continue
            except Exception:  # a failed delivery (or the database away for a moment) must not end the sender
                log.exception("webhook delivery failed")
            self._stop.wait(self.settings.webhook_poll_seconds)
