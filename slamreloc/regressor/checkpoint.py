"""Training checkpoints: resume an interrupted `slamreloc map` where it stopped.

A checkpoint holds the model, optimiser, lr schedule, weight-average and random-generator
states after a whole epoch, plus a fingerprint of the training data and recipe; it is only
resumed from when the fingerprint matches (same labels, same config). Written atomically;
loaded with torch's weights-only unpickler, so a checkpoint file cannot run code.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import torch

from slamreloc.errors import InputError
from slamreloc.io.outputs import atomic_file


def checkpoint_path(map_dir: str | Path) -> Path:
    """Where `slamreloc map --out MAP` keeps its training checkpoint: a hidden sibling of MAP."""
    map_dir = Path(map_dir)
    return map_dir.parent / f".{map_dir.name}.train-checkpoint.pt"


def fingerprint(descriptors: np.ndarray, points: np.ndarray, recipe: dict) -> str:
    """Hash of the training data and of everything in the recipe that shapes training."""
    h = hashlib.sha256()
    for a in (descriptors, points):
        a = np.ascontiguousarray(a)
        h.update(str((a.shape, a.dtype.str)).encode())
        h.update(a.tobytes())
    h.update(json.dumps(recipe, sort_keys=True, default=str).encode())
    return h.hexdigest()


def run_settings(**settings) -> dict[str, str]:
    """A run's settings as the checkpoint keeps them: each nested field as a dotted name ->
    its JSON text, so what a resumed run changed is found before its work and named."""
    flat: dict[str, str] = {}

    def walk(prefix: str, value) -> None:
        if isinstance(value, dict) and value:
            for key, item in value.items():
                walk(f"{prefix}.{key}" if prefix else str(key), item)
        else:
            flat[prefix] = json.dumps(value, sort_keys=True, default=str)

    walk("", settings)
    return flat


def check_settings(path: Path, settings: dict[str, str]) -> None:
    """Before a resumed run's work: InputError naming the first setting (`run_settings`) that
    differs from the interrupted run's. A checkpoint without settings (an older one) is left
    to the data fingerprint, checked when training starts."""
    saved = _read(path).get("settings")
    if not isinstance(saved, dict):
        return
    for key in sorted(set(saved) | set(settings)):
        if saved.get(key) != settings.get(key):
            raise InputError(f"{path}: checkpoint is from a run with another {key} "
                             f"({saved.get(key, 'unset')}, now {settings.get(key, 'unset')}); "
                             "run it with the interrupted run's settings, or without `resume` "
                             "to start anew")


def save_checkpoint(path: Path, fp: str, epoch: int, losses: list[float], model, opt, sched,
                    gen: torch.Generator, average, settings: dict[str, str] | None = None
                    ) -> None:
    state = {"fingerprint": fp, "settings": settings, "epoch": epoch, "losses": losses,
             "model": model.state_dict(), "optimizer": opt.state_dict(),
             "scheduler": sched.state_dict(), "generator": gen.get_state(),
             "average": average.state_dict()}
    with atomic_file(path) as tmp:
        torch.save(state, tmp)


def load_checkpoint(path: Path, fp: str) -> dict:
    """The checkpoint at `path`; InputError if it is unreadable or from other data/recipe."""
    state = _read(path)
    if state.get("fingerprint") != fp:
        raise InputError(f"{path}: checkpoint is from other training data or settings; "
                         "remove it or run without `resume`")
    return state


def _read(path: Path) -> dict:
    """The checkpoint's state; InputError if it is missing or unreadable."""
    if not path.is_file():
        raise InputError(f"{path}: no training checkpoint to resume from")
    from slamreloc.io.fileio import open_regular

    with open_regular(path, "training checkpoint") as f:
        try:
            state = torch.load(f, map_location="cpu", weights_only=True)
        except Exception as err:  # noqa: BLE001 - any unreadable file is the same user error
            raise InputError(f"{path}: unreadable training checkpoint "
                             f"({type(err).__name__})") from None
    if not isinstance(state, dict):
        raise InputError(f"{path}: unreadable training checkpoint (not a checkpoint's state)")
    return state
