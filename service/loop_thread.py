"""A background loop of the service (the job supervisor, the Celery reaper, the scene supervisor): a named
daemon thread started and stopped with the app."""

from __future__ import annotations

import threading
from collections.abc import Callable

STOP_WAIT_SECONDS = 10.0
"""How long stop() waits for the loop to see `stopping` and end (a pass in flight finishes first)."""


class LoopThread:
    """Runs `loop` in a daemon thread; the loop ends once it sees `stopping` set."""

    def __init__(self, name: str, loop: Callable[[], None]) -> None:
        self.name = name
        self.loop = loop
        self.stopping = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        self.stopping.clear()
        self._thread = threading.Thread(target=self.loop, name=self.name, daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self.stopping.set()
        if self._thread:
            self._thread.join(timeout=STOP_WAIT_SECONDS)

    def is_alive(self) -> bool:
        return self._thread is not None and self._thread.is_alive()
