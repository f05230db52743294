"""`sfmnerf serve` (being written)."""

import click


@click.command()
def serve() -> None:
    """Not implemented yet."""
    raise click.ClickException("not implemented yet")
