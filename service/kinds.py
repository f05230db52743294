"""Job kinds and job states: the words every floor of the service speaks (nothing below them).

Anything kept per kind (typed parameters, job functions, maximum runtimes) is a mapping checked complete
when its module is imported (`require_every_kind`), so a new kind cannot be half added.
"""

from __future__ import annotations

import enum
from collections.abc import Mapping


class JobState(enum.StrEnum):
    queued = "queued"
    running = "running"
    succeeded = "succeeded"
    failed = "failed"
    cancelled = "cancelled"


TERMINAL_STATES = frozenset({JobState.succeeded, JobState.failed, JobState.cancelled})


class JobKind(enum.StrEnum):
    reconstruction = "reconstruction"
    nerf = "nerf"
    video = "video"
    evaluation = "evaluation"


def require_every_kind(mapping: Mapping[JobKind, object], what: str) -> None:
    """Raises at start-up when a per-kind mapping misses a kind (or names one that does not exist)."""
    missing = [str(kind) for kind in JobKind if kind not in mapping]
    unknown = [str(key) for key in mapping if key not in set(JobKind)]
    if missing or unknown:
        raise RuntimeError(f"{what}: missing job kinds {missing}, unknown keys {unknown}")
