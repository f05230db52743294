"""The order in which the queue serves waiting jobs: round robin across the clients that own them."""

from __future__ import annotations

from collections import defaultdict, deque
from collections.abc import Iterable


def fair_order(queued: Iterable[tuple[str, str | None]], running: dict[str | None, int]) -> list[str]:
    """Job ids in the order the queue serves them: round robin across owners, the owner with the fewest
    running jobs first (ties: the one whose oldest job waits longest).

    `queued`: (job id, owner) oldest first; `running`: running jobs per owner."""
    waiting: dict[str | None, deque[str]] = defaultdict(deque)
    for job_id, owner in queued:
        waiting[owner].append(job_id)
    load = dict(running)
    arrival = {owner: index for index, owner in enumerate(waiting)}
    order = []
    while waiting:
        owner = min(waiting, key=lambda o: (load.get(o, 0), arrival[o]))
        order.append(waiting[owner].popleft())
        load[owner] = load.get(owner, 0) + 1
        if not waiting[owner]:
            del waiting[owner]
    return order
