"""Errors the SfM pipeline raises for bad input; each message names the file, line or reason."""


class InputError(ValueError):
    """The input (images, match files, calibration, options) is unusable; the message says where."""


class DegenerateConfigurationError(InputError):
    """The geometry is degenerate (too few matches, pure rotation, too little parallax)."""
