"""One reconstruction spread over the Celery workers: its SIFT feature extraction and matching run as tasks
over chunks of images and blocks of image pairs, its mapping on the job's own worker.

`CeleryStages` is the `estimation.features.sift.FeatureStages` of such a job. For each stage (extraction,
then matching) it writes what every chunk needs (the SIFT settings; for matching, every image's keypoints
and descriptors) and the list of chunks into the job's folder (`layout.SPREAD_DIR`/<attempt>/<stage>/),
sends one task per chunk (`SPREAD_TASK`, on the job queue), then works through the chunks itself from
the last one while the other workers take them from the first, and gathers the results in order: a chord's
fan-out and gather, with the job's worker one of the chord's workers (a worker only waiting for a chord
would hold its slot idle; with a single worker nobody would run the chunks). Each chunk is claimed once (a
file created exclusively, naming its worker process), and its result (<index>.pickle, renamed into place
when complete) or its exception (<index>.error, raised again by the job) is written beside the claim: the
data folder is shared by every worker. A chunk whose worker process died on the job's host is done again
by the job. The folder is removed when the reconstruction ends; a task that arrives after finds no stage
and does nothing.
"""

from __future__ import annotations

import functools
import os
import pickle
import shutil
import socket
import time
from collections import defaultdict
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

from service.celery_config import SPREAD_TASK, make_celery
from service.layout import SPREAD_DIR, job_dir
from service.settings import ServiceSettings
from service.store.leases import process_exists

STAGE_FILE = "stage.pickle"
POLL_SECONDS = 0.05
"""How often the job looks for a chunk result another worker is still computing."""
EXTRACTION, MATCHING = "extraction", "matching"


class SpreadError(RuntimeError):
    """A chunk of a spread reconstruction failed on the worker that ran it."""


@dataclass(frozen=True)
class Stage:
    """What every chunk of a stage needs (`shared`) and the chunks (`items`): image paths relative to the
    job's folder for extraction, query blocks for matching."""

    shared: Any
    items: list


class ChunkResult(NamedTuple):
    """What a chunk's function returned, and the CPU seconds of its worker process computing it."""

    result: list
    cpu_seconds: float


def spread_folder(settings: ServiceSettings, job_id: str, attempt: int) -> Path:
    return job_dir(settings, job_id) / SPREAD_DIR / str(attempt)


def _write_atomically(path: Path, data: bytes) -> None:
    partial = path.with_name(f".{path.name}.{os.getpid()}")
    partial.write_bytes(data)
    os.replace(partial, path)


def _claim(folder: Path, index: int) -> bool:
    """Whether this process took chunk `index` (nobody had)."""
    try:
        descriptor = os.open(folder / f"{index}.claim", os.O_CREAT | os.O_EXCL | os.O_WRONLY)
    except FileExistsError:
        return False
    with os.fdopen(descriptor, "w") as claim:
        claim.write(f"{socket.gethostname()} {os.getpid()}")
    return True


def _claimer(folder: Path, index: int) -> tuple[str, int] | None:
    """(host, pid) of the process that claimed chunk `index`, None while its claim is being written."""
    host, _, pid = (folder / f"{index}.claim").read_text().partition(" ")
    return (host, int(pid)) if pid else None


def _load_stage(path: Path) -> Stage:
    """The stage of `path`, read once per process while the file stays the same (a matching stage holds
    every image's descriptors)."""
    status = path.stat()
    return _read_stage(path, status.st_ino, status.st_mtime_ns)


@functools.lru_cache(maxsize=1)
def _read_stage(path: Path, inode: int, modified_ns: int) -> Stage:
    return pickle.loads(path.read_bytes())


def _run_chunk(job_folder: Path, stage_name: str, index: int) -> None:
    """Computes chunk `index` of the stage and writes its result with the CPU seconds it took, or its
    error."""
    from estimation.features.sift import extract_chunk, match_block

    folder = job_folder / stage_name
    stage = _load_stage(folder / STAGE_FILE)
    item = stage.items[index]
    started = time.process_time()
    try:
        if stage_name == EXTRACTION:
            result = extract_chunk([job_folder.parents[1] / path for path in item], stage.shared)
        else:
            result = match_block(stage.shared, item)
    except Exception as error:  # the job raises it (an InputError naming a file stays one)
        try:
            raised = pickle.dumps(error)
        except Exception:  # an exception that cannot be pickled
            raised = pickle.dumps(SpreadError(f"{stage_name} chunk {index}: {type(error).__name__}: {error}"))
        _write_atomically(folder / f"{index}.error", raised)
    else:
        done = ChunkResult(result, time.process_time() - started)
        _write_atomically(folder / f"{index}.pickle", pickle.dumps(done, protocol=pickle.HIGHEST_PROTOCOL))


def run_spread_task(job_id: str, attempt: int, stage_name: str, index: int) -> None:
    """The Celery task: chunk `index` of a stage of the job's attempt, unless someone claimed it or the
    stage is gone (the reconstruction ended)."""
    folder = spread_folder(ServiceSettings(), job_id, attempt)
    if (folder / stage_name / STAGE_FILE).exists() and _claim(folder / stage_name, index):
        _run_chunk(folder, stage_name, index)


class CeleryStages:
    """The extraction chunks and matching blocks of a job's reconstruction as Celery tasks (see the module);
    `close` removes their files."""

    def __init__(self, settings: ServiceSettings, job_id: str, attempt: int, log: Callable[[str], None]
                 ) -> None:
        self.images_per_chunk = settings.spread_images_per_chunk
        self.pairs_per_block = settings.spread_pairs_per_block
        self._celery = make_celery(settings)
        self._job_id, self._attempt = job_id, attempt
        self._folder = spread_folder(settings, job_id, attempt)
        self._log = log
        self.cpu_seconds: dict[str, list[float]] = {}
        """Per stage run, the CPU seconds each worker process spent on its chunks."""

    def extract(self, chunks: list[list[Path]], config: Any) -> Iterator[list]:
        job = self._folder.parents[1]
        return self._run(EXTRACTION, config, [[path.resolve().relative_to(job.resolve()) for path in chunk]
                                                  for chunk in chunks])

    def match(self, work: Any, blocks: list[list]) -> Iterator[list]:
        return self._run(MATCHING, work, blocks)

    def close(self) -> None:
        """Removes the stages' files (an earlier attempt's too)."""
        shutil.rmtree(self._folder.parent, ignore_errors=True)

    def _run(self, stage_name: str, shared: Any, items: list) -> Iterator[list]:
        folder = self._folder / stage_name
        shutil.rmtree(folder, ignore_errors=True)
        folder.mkdir(parents=True)
        _write_atomically(folder / STAGE_FILE, pickle.dumps(Stage(shared, items), pickle.HIGHEST_PROTOCOL))
        for index in range(len(items)):
            self._celery.send_task(SPREAD_TASK, args=[self._job_id, self._attempt, stage_name, index])
        for index in reversed(range(len(items))):  # the other workers take them from the first
            if _claim(folder, index):
                _run_chunk(self._folder, stage_name, index)
        per_process: dict[tuple[str, int] | None, float] = defaultdict(float)
        for index in range(len(items)):
            done = self._result(folder, stage_name, index)
            per_process[_claimer(folder, index)] += done.cpu_seconds
            yield done.result
        self.cpu_seconds[stage_name] = list(per_process.values())
        self._log(f"{stage_name}: {len(items)} chunks done by {len(per_process)} worker processes (CPU "
                  f"seconds each: {', '.join(f'{seconds:.1f}' for seconds in per_process.values())})")

    def _result(self, folder: Path, stage_name: str, index: int) -> ChunkResult:
        """Chunk `index`'s result, once its worker wrote it."""
        while True:
            if (folder / f"{index}.pickle").exists():
                return pickle.loads((folder / f"{index}.pickle").read_bytes())
            if (folder / f"{index}.error").exists():
                raise pickle.loads((folder / f"{index}.error").read_bytes())
            claimer = _claimer(folder, index)
            if claimer is not None and claimer[0] == socket.gethostname() and not process_exists(claimer[1]):
                _run_chunk(self._folder, stage_name, index)  # its worker process died
                continue
            time.sleep(POLL_SECONDS)
