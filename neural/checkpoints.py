"""Checkpoint files of a training run: save (keeping the latest and the best), list, load, restore.

Layout: RUN/checkpoints/step_0000100.pt plus RUN/checkpoints/index.json naming the latest and the best
(highest validation PSNR; the latest when there is no validation). Other step files are deleted.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from neural.errors import CheckpointError

#: Bumped whenever the checkpoint layout changes incompatibly.
CHECKPOINT_FORMAT_VERSION = 1
INDEX_FILE = "index.json"
CHECKPOINT_READ_ATTEMPTS = 3  # reads racing a trainer that replaces its latest checkpoint


@dataclass(frozen=True)
class CheckpointInfo:
    """One kept checkpoint of a run."""

    step: int
    path: Path
    is_latest: bool
    is_best: bool
    val_psnr: float | None


def checkpoint_dir(run_dir: Path) -> Path:
    return Path(run_dir) / "checkpoints"


def checkpoint_name(step: int) -> str:
    return f"step_{step:07d}.pt"


def read_index(run_dir: Path) -> dict[str, Any]:
    path = checkpoint_dir(run_dir) / INDEX_FILE
    if not path.is_file():
        return {}
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as error:
        raise CheckpointError(f"{path}: corrupt checkpoint index ({error})") from None


def save_checkpoint(run_dir: Path, payload: dict[str, Any], step: int, val_psnr: float | None) -> Path:
    """Write payload as step_<step>.pt, mark it latest (and best if its val PSNR is the highest), prune."""
    folder = checkpoint_dir(run_dir)
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / checkpoint_name(step)
    temporary = path.with_suffix(".tmp")
    stamped = {**payload, "format_version": CHECKPOINT_FORMAT_VERSION, "step": step, "val_psnr": val_psnr}
    torch.save(stamped, temporary)
    os.replace(temporary, path)  # a crash mid-write never leaves a truncated "latest"

    index = read_index(run_dir)
    entry = {"step": step, "file": path.name, "val_psnr": val_psnr}
    best = index.get("best")
    if best is None or (val_psnr is not None and (best["val_psnr"] is None or val_psnr > best["val_psnr"])):
        best = entry
    elif best["val_psnr"] is None and val_psnr is None:
        best = entry  # without validation the best is simply the newest
    index = {"latest": entry, "best": best}
    index_path = folder / INDEX_FILE
    index_path.with_suffix(".tmp").write_text(json.dumps(index, indent=2))
    os.replace(index_path.with_suffix(".tmp"), index_path)
    keep = {index["latest"]["file"], index["best"]["file"]}
    for old in folder.glob("step_*.pt"):
        if old.name not in keep:
            old.unlink()
    return path


def list_checkpoints(run_dir: Path | str) -> list[CheckpointInfo]:
    """The run's kept checkpoints, oldest first; empty if it has none."""
    index = read_index(Path(run_dir))
    if not index:
        return []
    folder = checkpoint_dir(Path(run_dir))
    entries = {index["latest"]["file"]: index["latest"], index["best"]["file"]: index["best"]}
    infos = [
        CheckpointInfo(
            step=entry["step"],
            path=folder / name,
            is_latest=name == index["latest"]["file"],
            is_best=name == index["best"]["file"],
            val_psnr=entry["val_psnr"],
        )
        for name, entry in entries.items()
    ]
    return sorted(infos, key=lambda info: info.step)


def resolve_checkpoint(run_dir: Path, which: str = "latest") -> Path:
    """ "latest", "best", a step number, or a path to a .pt file -> the checkpoint file."""
    candidate = Path(which)
    if candidate.suffix == ".pt":
        if not candidate.is_file():
            raise CheckpointError(f"{candidate}: checkpoint file not found")
        return candidate
    infos = list_checkpoints(run_dir)
    if not infos:
        raise CheckpointError(f"{run_dir}: no checkpoints (expected {checkpoint_dir(run_dir) / INDEX_FILE})")
    for info in infos:
        if (
            (which == "latest" and info.is_latest)
            or (which == "best" and info.is_best)
            or which == str(info.step)
        ):
            if not info.path.is_file():
                raise CheckpointError(f"{info.path}: listed in {INDEX_FILE} but missing")
            return info.path
    raise CheckpointError(f"{run_dir}: no checkpoint {which!r} (have steps {[i.step for i in infos]})")


def load_named_checkpoint(
    run_dir: Path, which: str = "latest", map_location: torch.device | str = "cpu"
) -> tuple[Path, dict[str, Any]]:
    """resolve_checkpoint then load_checkpoint, safe against a trainer that is writing the run right now.

    The trainer saves the new latest, rewrites the index, then deletes the old file: a reader that resolved
    the old name just before can find it gone. If the index changed meanwhile, resolve again.
    """
    for _ in range(CHECKPOINT_READ_ATTEMPTS - 1):
        index = read_index(run_dir)
        try:
            path = resolve_checkpoint(run_dir, which)
            return path, load_checkpoint(path, map_location=map_location)
        except CheckpointError:
            if read_index(run_dir) == index:
                raise  # nothing moved under us: the error is real
    path = resolve_checkpoint(run_dir, which)
    return path, load_checkpoint(path, map_location=map_location)


def load_checkpoint(path: Path, map_location: torch.device | str = "cpu") -> dict[str, Any]:
    """A checkpoint written by save_checkpoint; CheckpointError if it is not one or of another version."""
    try:
        # Our own files: they hold numpy/python RNG states, which the weights-only loader refuses.
        payload = torch.load(path, map_location=map_location, weights_only=False)
    except Exception as error:  # torch raises many types for a corrupt or foreign file
        raise CheckpointError(
            f"{path}: not a readable checkpoint ({type(error).__name__}: {error})"
        ) from None
    if not isinstance(payload, dict) or "format_version" not in payload:
        raise CheckpointError(f"{path}: not an sfmnerf checkpoint (no format_version)")
    if payload["format_version"] != CHECKPOINT_FORMAT_VERSION:
        raise CheckpointError(
            f"{path}: checkpoint format version {payload['format_version']} is incompatible with this "
            f"version of sfmnerf (expects {CHECKPOINT_FORMAT_VERSION})"
        )
    return payload


def load_model_state(model: torch.nn.Module, state: dict[str, torch.Tensor], where: Path | str) -> None:
    """Load a state dict, first resizing tensors whose shape the model changed while training (grids).

    A submodule with an `upgrade_state(state, prefix)` method first fills in what older versions did not save.
    """
    state = dict(state)
    for name, module in model.named_modules():
        upgrade = getattr(module, "upgrade_state", None)
        if upgrade is not None:
            upgrade(state, f"{name}." if name else "")
    own = model.state_dict()
    unknown = sorted(set(state) - set(own))
    missing = sorted(set(own) - set(state))
    if unknown or missing:
        raise CheckpointError(
            f"{where}: checkpoint does not fit this model (unexpected: {unknown[:5]}, "
            f"missing: {missing[:5]}); was it written by another model or version?"
        )
    for name, tensor in state.items():
        if own[name].shape == tensor.shape:
            continue
        module_path, _, attribute = name.rpartition(".")
        module = model.get_submodule(module_path) if module_path else model
        current = getattr(module, attribute)
        resized = torch.empty(tensor.shape, dtype=current.dtype, device=current.device)
        if isinstance(current, torch.nn.Parameter):
            setattr(module, attribute, torch.nn.Parameter(resized, requires_grad=current.requires_grad))
        else:
            module._buffers[attribute] = resized
    try:
        model.load_state_dict(state)
    except RuntimeError as error:
        raise CheckpointError(f"{where}: checkpoint does not fit this model ({error})") from None
