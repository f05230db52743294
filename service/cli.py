"""The `sfmnerf` command line: one group, each command defined next to the code it drives."""

import click

from service.commands.calibrate import calibrate
from service.commands.db import db
from service.commands.nerf import nerf
from service.commands.reconstruct import reconstruct
from service.commands.scene import scene
from service.commands.serve import serve


@click.group()
@click.version_option(package_name="sfmnerf")
def main() -> None:
    """Photographs to 3D: Structure from Motion and Neural Radiance Fields."""


main.add_command(reconstruct)
main.add_command(nerf)
main.add_command(serve)
main.add_command(calibrate)
main.add_command(scene)
main.add_command(db)
