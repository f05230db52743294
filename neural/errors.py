"""Errors raised on bad NeRF input; each message names the file, field or reason."""


class DatasetError(ValueError):
    """A dataset is unusable (missing file or key, non-rigid pose, mixed image sizes, empty split)."""


class CheckpointError(ValueError):
    """A run or checkpoint is unusable (missing, another model, incompatible version, corrupt)."""
