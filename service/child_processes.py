"""The API's helper processes (validation and render processes) end with the API, even after a kill -9.

Each one calls `become_child_of(parent_pid, data_dir)` first: it asks for the parent-death signal (Linux;
a watchdog thread polls the parent elsewhere) and leaves a pid file `DATA/processes/<API pid>/<pid>`
holding its start time. At start-up `reap_leftovers(data_dir)` ends the processes listed for an API that
is gone (or for this very pid: a restarted container reuses it) whose start time still matches, so a
pid the system has given to another program since is never touched. Job processes have their own record
(the job store's pid, see service.executor) and the same parent-death signal (service.worker).
"""

from __future__ import annotations

import atexit
import contextlib
import logging
import os
import shutil
import signal
from pathlib import Path

from estimation.parallel import die_with_parent

log = logging.getLogger(__name__)
PROCESSES_DIR = "processes"


def start_time(pid: int) -> str | None:
    """The process's start time in clock ticks since boot (/proc/PID/stat field 22); None if not running."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    fields = stat.rsplit(")", 1)[1].split()
    return None if fields[0] == "Z" else fields[19]


def children_dir(data_dir: Path, parent_pid: int) -> Path:
    return data_dir / PROCESSES_DIR / str(parent_pid)


def become_child_of(parent_pid: int, data_dir: Path) -> None:
    """Ends this process with its parent; records it for `reap_leftovers` until it exits normally."""
    die_with_parent(parent_pid)
    started = start_time(os.getpid())
    if started is None:  # no /proc: the watchdog is the only guard
        return
    record = children_dir(data_dir, parent_pid) / str(os.getpid())
    record.parent.mkdir(parents=True, exist_ok=True)
    record.write_text(started)
    atexit.register(record.unlink, missing_ok=True)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def reap_leftovers(data_dir: Path) -> list[int]:
    """Kills the recorded helper processes of APIs that no longer run; returns their pids."""
    killed = []
    root = data_dir / PROCESSES_DIR
    for folder in sorted(root.iterdir()) if root.is_dir() else []:
        if not folder.name.isdigit():
            continue
        parent = int(folder.name)
        if parent != os.getpid() and _alive(parent):
            continue  # another API on the same data folder: its processes are its own
        for record in folder.iterdir():
            if not record.name.isdigit():
                continue
            pid = int(record.name)
            recorded = record.read_text().strip()
            if recorded and start_time(pid) == recorded:
                with contextlib.suppress(OSError):
                    os.kill(pid, signal.SIGKILL)
                    killed.append(pid)
        shutil.rmtree(folder, ignore_errors=True)
    if killed:
        log.warning("ended %d process(es) left by a stopped API: %s", len(killed), killed)
    return killed
