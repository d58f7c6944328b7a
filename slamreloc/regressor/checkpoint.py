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


def restore_checkpoint(path: Path, state: dict, epochs: int, model, opt, sched,
                       gen: torch.Generator, average) -> tuple[int, list[float]]:
    """Put a loaded checkpoint's `state` (`load_checkpoint`) into the training objects; returns
    (the epoch to start at, the losses of the epochs before it). InputError naming `path` and
    the field where the state is not one a run of `epochs` epochs of this model writes: an
    epoch outside 0..epochs, losses that are not one finite number a finished epoch, weights
    that are not finite, or states the model, optimiser, schedule, generator or weight
    average cannot take (a fingerprint is plain text in the file: anyone can copy it)."""
    epoch, losses = state.get("epoch"), state.get("losses")
    if type(epoch) is not int or not 0 <= epoch <= epochs:
        raise InputError(f"{path}: unreadable training checkpoint ('epoch' must be a whole "
                         f"number in 0..{epochs}, got {str(epoch)[:40]})")
    if (not isinstance(losses, list) or len(losses) != epoch
            or not all(type(v) in (int, float) and np.isfinite(v) for v in losses)):
        raise InputError(f"{path}: unreadable training checkpoint ('losses' must be {epoch} "
                         "finite numbers, one a finished epoch)")
    weights = state.get("model")
    if isinstance(weights, dict) and not all(
            not torch.is_tensor(t) or not t.is_floating_point() or bool(torch.isfinite(t).all())
            for t in weights.values()):
        raise InputError(f"{path}: unreadable training checkpoint ('model' holds NaN or "
                         "infinite weights)")
    # what this run's recipe fixes (the rate changes along the schedule, the rest does not)
    groups = [{k: v for k, v in g.items() if k not in ("params", "lr", "initial_lr")}
              for g in opt.state_dict()["param_groups"]]
    schedule = {k: sched.state_dict()[k] for k in ("step_size", "gamma", "base_lrs")}
    for key, target in (("model", model), ("optimizer", opt), ("scheduler", sched),
                        ("average", average), ("generator", gen)):
        try:
            if key == "generator":
                gen.set_state(state[key])
            else:
                target.load_state_dict(state[key])
            problem = _restored_problem(key, opt, sched, groups, schedule)
        except Exception as err:  # noqa: BLE001 - torch's loaders raise many kinds
            problem = type(err).__name__
        if problem:
            raise InputError(f"{path}: unreadable training checkpoint ('{key}': "
                             f"{problem})") from None
    return epoch, [float(v) for v in losses]


def _restored_problem(key: str, opt, sched, groups: list[dict], schedule: dict) -> str | None:
    """Why the optimiser or schedule just restored is not this run's (None: it is): other
    hyper-parameters, moments of another shape than their parameter or not finite, a step
    count that is not a whole number."""
    if key == "optimizer":
        now = opt.state_dict()["param_groups"]
        if [{k: v for k, v in g.items() if k not in ("params", "lr", "initial_lr")}
                for g in now] != groups or not all(
                    type(g["lr"]) is float and 0 < g["lr"] < float("inf") for g in now):
            return "another optimiser's settings"
        for param, moments in opt.state.items():
            for name, value in moments.items():
                if torch.is_tensor(value) and (
                        value.dim() and value.shape != param.shape
                        or value.is_floating_point() and not bool(torch.isfinite(value).all())):
                    return f"its {name} does not fit the model"
    if key == "scheduler":
        now = sched.state_dict()
        if {k: now[k] for k in schedule} != schedule or not all(
                type(now[k]) is int and now[k] >= 0 for k in ("last_epoch", "_step_count")):
            return "another schedule"
    return None


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
