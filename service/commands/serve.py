"""`sfmnerf serve`: the REST service with its embedded defaults (SQLite file, local job processes)."""

from __future__ import annotations

from pathlib import Path

import click

SHUTDOWN_GRACE_SECONDS = 5.0
"""On SIGTERM, requests still running after this long are cancelled (renders waiting in a full queue held
the exit for ~50 s), then the running jobs are stopped and re-queued."""


@click.command()
@click.option("--host", default="127.0.0.1", show_default=True, help="Address to listen on.")
@click.option("--port", default=8000, show_default=True, type=click.IntRange(1, 65535), help="TCP port.")
@click.option(
    "--data-dir",
    type=click.Path(file_okay=False, path_type=Path),
    default=None,
    help="Data folder (default: SFMNERF_DATA_DIR or ./data).",
)
@click.option(
    "--concurrency",
    type=click.IntRange(1, 64),
    default=None,
    help="Jobs run at the same time (default: SFMNERF_CONCURRENCY or 1).",
)
@click.option(
    "--log-level",
    default="info",
    show_default=True,
    type=click.Choice(["critical", "error", "warning", "info", "debug"]),
)
def serve(host: str, port: int, data_dir: Path | None, concurrency: int | None, log_level: str) -> None:
    """Start the REST API (docs at http://HOST:PORT/docs); settings come from SFMNERF_* variables."""
    import uvicorn

    from service.app import create_app
    from service.settings import ServiceSettings

    overrides = {k: v for k, v in {"data_dir": data_dir, "concurrency": concurrency}.items() if v is not None}
    settings = ServiceSettings(**overrides)
    click.echo(
        f"sfmnerf: data in {settings.data_dir}, executor {settings.executor}, "
        f"database {settings.resolved_database_url.split('@')[-1]}"
    )
    uvicorn.run(
        create_app(settings),
        host=host,
        port=port,
        log_level=log_level,
        timeout_graceful_shutdown=SHUTDOWN_GRACE_SECONDS,
    )
