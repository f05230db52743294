"""Service settings, read from environment variables prefixed with SFMNERF_ (pydantic-settings).

Every field is documented in docs/service.md's settings table; the defaults give the embedded setup
(`sfmnerf serve`: a SQLite file and local worker processes, nothing else to install or start).
"""

from __future__ import annotations

from functools import cached_property
from ipaddress import IPv4Network, IPv6Network
from pathlib import Path
from typing import Literal

from pydantic import Field, SecretStr, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from service.kinds import JobKind, require_every_kind

WORKER_SETTINGS_ENV = "SFMNERF_WORKER_SETTINGS_JSON"
"""Environment variable through which the local executor hands its settings to a job process."""
LOCAL_HOST_NAMES = ("localhost", "*.localhost", "127.0.0.1", "::1")
"""The names an open service (no token) answers to by default: only this machine's."""


class ServiceSettings(BaseSettings):
    """Configuration of the REST service, its job store and its executors."""

    model_config = SettingsConfigDict(env_prefix="SFMNERF_", extra="ignore")

    data_dir: Path = Field(Path("data"), description="Folder holding every job's uploads and outputs.")
    database_url: str | None = Field(
        None,
        description="SQLAlchemy URL of the job store; default: a SQLite file `sfmnerf.sqlite` in data_dir. "
        "PostgreSQL: postgresql+psycopg://user:password@host/db.",
    )
    executor: Literal["local", "celery"] = Field(
        "local", description="local: job processes supervised by the API; celery: Celery workers via broker."
    )
    broker_url: str = Field("redis://127.0.0.1:6379/0", description="Celery broker URL (executor=celery).")
    broker_visibility_timeout_seconds: float | None = Field(
        None,
        gt=0,
        description="Redis visibility timeout of Celery messages; default: the longest maximum runtime "
        "of a job kind plus one hour, so a long job's message is never handed to a second worker.",
    )
    concurrency: int = Field(1, ge=1, description="Jobs run at the same time by the local executor.")
    spread_min_images: int = Field(
        100,
        ge=2,
        description="With executor=celery, a SIFT reconstruction of at least this many images spreads its "
        "feature extraction and matching over the Celery workers (chunks of images, blocks of image pairs); "
        "the mapping stays on the job's worker.",
    )
    spread_images_per_chunk: int = Field(
        8, ge=1, description="Images per feature-extraction task of a spread reconstruction."
    )
    spread_pairs_per_block: int = Field(
        300, ge=1, description="Image pairs (at least) per matching task of a spread reconstruction."
    )
    job_threads: int | None = Field(
        None,
        ge=1,
        description="CPU threads of one local job process (torch/OpenMP); default: cores / concurrency.",
    )
    max_upload_bytes: int = Field(512 * 2**20, ge=1, description="Largest accepted request body, bytes.")
    max_images: int = Field(500, ge=2, description="Most images in one reconstruction upload.")
    max_image_pixels: int = Field(40_000_000, ge=1, description="Most pixels (width x height) of one image.")
    max_zip_entries: int = Field(5000, ge=1, description="Most files in an uploaded dataset zip.")
    max_input_video_bytes: int = Field(
        400 * 2**20, ge=1, description="Largest video uploaded in place of photos, bytes."
    )
    max_input_video_seconds: float = Field(
        300.0, gt=0, description="Longest video uploaded in place of photos, seconds."
    )
    max_input_video_pixels: int = Field(
        3840 * 2160, ge=1, description="Most pixels (width x height) of a frame of an uploaded video."
    )
    max_zip_uncompressed_bytes: int = Field(
        2 * 2**30, ge=1, description="Largest total uncompressed size of an uploaded dataset zip, bytes."
    )
    max_zip_ratio: float = Field(
        200.0, gt=1, description="Largest compression ratio of one zip entry (zip-bomb guard)."
    )
    max_json_bytes: int = Field(
        1 * 2**20,
        ge=1,
        description="Largest accepted body of a request that is not a multipart upload, bytes.",
    )
    validation_memory_bytes: int = Field(
        512 * 2**20,
        ge=2**27,
        description="Address space of the process that decodes and checks an upload; an upload whose "
        "headers say it needs more is refused (413) before it is decompressed.",
    )
    validation_timeout_seconds: float = Field(
        300.0, gt=0, description="Longest time the check of one upload may take (over it: 413)."
    )
    max_render_pixels: int = Field(
        2_000_000, ge=1, description="Most pixels (width x height) of one render or video frame."
    )
    api_token: SecretStr | None = Field(
        None,
        description="The admin token: when set, every route but the health checks needs "
        "`Authorization: Bearer TOKEN`; its holder sees every job.",
    )
    clients_file: Path | None = Field(
        None,
        description="File of named client tokens, one `name:sha256:HEX` line each "
        "(HEX: SHA-256 of the token); "
        "a client sees only its own jobs.",
    )
    docs: Literal["token", "public", "off"] = Field(
        "token",
        description="/docs, /redoc and /openapi.json: token (need a token like /v1 when auth is configured), "
        "public (open to all) or off (not served).",
    )
    cancel_grace_seconds: float = Field(
        2.0, ge=0, description="Seconds between SIGTERM and SIGKILL when a job process is cancelled."
    )
    heartbeat_seconds: float = Field(5.0, gt=0, description="How often a running job writes a heartbeat.")
    heartbeat_timeout_seconds: float = Field(
        120.0, gt=0, description="A celery job silent for this long is marked failed (its worker died)."
    )
    supervisor_lease_seconds: float = Field(
        15.0,
        gt=0,
        description="A local supervisor (one per API process) renews its lease 3 times in this period; "
        "its running jobs are taken over by another API process on the same database once it lapses.",
    )
    max_runtime_reconstruction_minutes: float = Field(
        120.0, gt=0, description="A reconstruction job running longer fails with this reason."
    )
    max_runtime_nerf_minutes: float = Field(
        1440.0, gt=0, description="A NeRF training job running longer fails with this reason."
    )
    max_runtime_video_minutes: float = Field(
        120.0, gt=0, description="An orbit video job running longer fails with this reason."
    )
    max_runtime_evaluation_minutes: float = Field(
        120.0, gt=0, description="A held-out evaluation job (a scene's last stage) running longer fails "
        "with this reason."
    )
    job_retention_minutes: float = Field(
        2880.0,
        gt=0,
        description="Finished jobs and their files are deleted this long after they ended, unless pinned.",
    )
    min_free_disk_bytes: int = Field(
        1 * 2**30, ge=0, description="New jobs and uploads are refused (507) below this free space."
    )
    render_workers: int = Field(
        1, ge=1, description="Long-lived render processes of the local executor (each caches a model)."
    )
    render_queue_size: int = Field(
        8, ge=1, description="Renders waiting or running at once; more are answered 503 with Retry-After."
    )
    render_timeout_seconds: float = Field(120.0, gt=0, description="A render taking longer fails (504).")
    render_cache_per_job: int = Field(
        64, ge=0, description="Renders kept per NeRF job to answer identical requests (0: no cache)."
    )
    max_video_pixels: int = Field(
        50_000_000,
        ge=1,
        description="Budget of one orbit video: frames x width x height (e.g. 36 frames of 200x200 = 1.44M).",
    )
    webhook_attempts: int = Field(5, ge=1, description="Attempts to deliver a job's webhook.")
    webhook_backoff_seconds: float = Field(
        1.0, ge=0, description="First delay between webhook attempts; doubles after each failure."
    )
    webhook_timeout_seconds: float = Field(10.0, gt=0, description="Timeout of one webhook attempt.")
    webhook_poll_seconds: float = Field(
        1.0, gt=0, description="How often an idle API process looks for webhooks due (the persistent outbox)."
    )
    webhook_allowed_networks: list[IPv4Network | IPv6Network] = Field(
        default_factory=list,
        description="Networks webhooks may reach although they are not public (loopback, private, ...), "
        'as JSON, e.g. ["10.0.0.0/8"].',
    )

    validation_workers: int = Field(
        2,
        ge=1,
        description="Upload checks (one process each) running at once; more get 429 with Retry-After.",
    )
    max_queued_jobs_per_client: int = Field(
        20, ge=1, description="Jobs a named client may have waiting; more are answered 429 with Retry-After."
    )
    max_disk_bytes_per_client: int = Field(
        20 * 2**30, ge=0, description="Bytes a named client's jobs may take on disk; more: new work gets 507."
    )
    trusted_hosts: list[str] | None = Field(
        None,
        description="Host names the service answers to (other Host headers: 400, against DNS rebinding), "
        'as JSON, e.g. ["api.example.org", "*.example.org"]; "*": any. Default: the localhost names '
        "when no token is configured, any host otherwise.",
    )

    @field_validator("api_token", "database_url", "clients_file", mode="before")
    @classmethod
    def _empty_is_unset(cls, value: object) -> object:
        # compose files pass unset variables as "": that means "not configured", not "the empty token".
        return None if value == "" else value

    @field_validator("data_dir")
    @classmethod
    def _absolute(cls, value: Path) -> Path:
        # Job processes and Celery workers may run from another working directory.
        return value.expanduser().resolve()

    @cached_property
    def resolved_database_url(self) -> str:
        """The configured database URL, or the default SQLite file inside the data folder."""
        if self.database_url:
            return self.database_url
        return f"sqlite:///{self.data_dir / 'sfmnerf.sqlite'}"

    @property
    def jobs_dir(self) -> Path:
        return self.data_dir / "jobs"

    def limits(self) -> dict[str, int | float]:
        """The input limits clients should know about (shown by GET /v1/info)."""
        return {
            "max_upload_bytes": self.max_upload_bytes,
            "max_images": self.max_images,
            "max_image_pixels": self.max_image_pixels,
            "max_zip_entries": self.max_zip_entries,
            "max_zip_uncompressed_bytes": self.max_zip_uncompressed_bytes,
            "max_json_bytes": self.max_json_bytes,
            "max_render_pixels": self.max_render_pixels,
            "max_video_pixels": self.max_video_pixels,
            "max_input_video_bytes": self.max_input_video_bytes,
            "max_input_video_seconds": self.max_input_video_seconds,
            "max_input_video_pixels": self.max_input_video_pixels,
            "max_queued_jobs_per_client": self.max_queued_jobs_per_client,
            "max_disk_bytes_per_client": self.max_disk_bytes_per_client,
        }

    def effective_trusted_hosts(self) -> list[str]:
        """SFMNERF_TRUSTED_HOSTS, or its default: localhost names when open, any host behind a token."""
        if self.trusted_hosts is not None:
            return [host.lower() for host in self.trusted_hosts]
        if self.api_token is None and self.clients_file is None:
            return list(LOCAL_HOST_NAMES)
        return ["*"]

    def max_runtime_seconds(self, kind: str) -> float:
        """The longest a job of this kind may run (SFMNERF_MAX_RUNTIME_<KIND>_MINUTES)."""
        return 60.0 * getattr(self, MAX_RUNTIME_FIELD[JobKind(kind)])

    @property
    def longest_job_seconds(self) -> float:
        return max(self.max_runtime_seconds(kind) for kind in JobKind)

    def threads_per_job(self) -> int:
        """CPU threads each local job process may use, so concurrent jobs do not oversubscribe the cores."""
        import os

        return self.job_threads or max(1, (os.cpu_count() or 1) // self.concurrency)

    def to_worker_json(self) -> str:
        """Serialized settings for a child job process (the API token stays with the API)."""
        return self.model_dump_json(exclude={"api_token"})


MAX_RUNTIME_FIELD: dict[JobKind, str] = {
    JobKind.reconstruction: "max_runtime_reconstruction_minutes",
    JobKind.nerf: "max_runtime_nerf_minutes",
    JobKind.video: "max_runtime_video_minutes",
    JobKind.evaluation: "max_runtime_evaluation_minutes",
}
"""The setting that limits each job kind's runtime (the one per-kind limit)."""


def _check_max_runtime_fields() -> None:
    """At start-up: every kind has its maximum runtime, and each names a real setting."""
    require_every_kind(MAX_RUNTIME_FIELD, "maximum runtime settings")
    missing = set(MAX_RUNTIME_FIELD.values()) - set(ServiceSettings.model_fields)
    if missing:
        raise RuntimeError(f"maximum runtime settings: no field {sorted(missing)} in ServiceSettings")


_check_max_runtime_fields()
