"""`sfmnerf reconstruct` (being written)."""

import click


@click.command()
def reconstruct() -> None:
    """Not implemented yet."""
    raise click.ClickException("not implemented yet")
