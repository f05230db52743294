"""`sfmnerf nerf ...` (being written)."""

import click


@click.group()
def nerf() -> None:
    """Neural radiance fields: train, render, eval."""
