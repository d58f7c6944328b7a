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


def restore_checkpoint(path: Path, state: dict, epochs: int, steps_per_epoch: int, model,
                       opt, sched, gen: torch.Generator, average) -> tuple[int, list[float]]:
    """Put a loaded checkpoint's `state` (`load_checkpoint`) into the training objects; returns
    (the epoch to start at, the losses of the epochs before it). InputError naming `path` and
    the field where the state is not one this run (`epochs` epochs of `steps_per_epoch`
    optimiser steps, this model and recipe) writes: an epoch outside 0..epochs, losses that
    are not one finite number a finished epoch, weights that are not finite, states the model,
    optimiser, schedule, generator or weight average cannot take, or that another run would
    hold at that epoch (a rate or a step count off the schedule, moments of another shape or
    sign, an average of other epochs). A fingerprint is plain text in the file: anyone can
    copy it, so the state itself is checked."""
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
    run = _Run(epoch, steps_per_epoch, opt, sched, average)
    for key, target in (("model", model), ("scheduler", sched), ("optimizer", opt),
                        ("average", average), ("generator", gen)):
        try:
            if key == "generator":
                gen.set_state(state[key])
            else:
                target.load_state_dict(state[key])
            problem = run.problem(key)
        except Exception as err:  # noqa: BLE001 - torch's loaders raise many kinds
            problem = f"not a state this run's {key} takes ({type(err).__name__})"
        if problem:
            raise InputError(f"{path}: unreadable training checkpoint ('{key}': "
                             f"{problem})") from None
    return epoch, [float(v) for v in losses]


class _Run:
    """What the training objects of a run resumed at `epoch` must hold once restored: the
    recipe's hyper-parameters (made before the restore), a schedule `epoch` epochs of
    `steps_per_epoch` steps in (an interrupted epoch's steps included), the optimiser's steps
    and rate on it, the weight average of the epochs of its tail finished."""

    _FREE = ("params", "lr", "initial_lr")  # what a group may hold other than the recipe's

    def __init__(self, epoch: int, steps_per_epoch: int, opt, sched, average) -> None:
        self.epoch, self.steps_per_epoch = epoch, steps_per_epoch
        self.opt, self.sched, self.average = opt, sched, average
        self.groups = self._groups()
        self.schedule = {k: sched.state_dict()[k] for k in ("step_size", "gamma", "base_lrs")}

    def _groups(self) -> list[dict]:
        return [{k: v for k, v in g.items() if k not in self._FREE}
                for g in self.opt.state_dict()["param_groups"]]

    def problem(self, key: str) -> str | None:
        """Why the object `key` just restored is not this run's (None: it is)."""
        if key == "optimizer":
            if self._groups() != self.groups:
                return "another optimiser's settings"
            for param, moments in self.opt.state.items():
                for name, value in moments.items():
                    if not torch.is_tensor(value):
                        continue
                    if value.dim() and value.shape != param.shape or (
                            value.is_floating_point() and not bool(torch.isfinite(value).all())):
                        return f"its {name} does not fit the model"
                    if name in ("step", "exp_avg_sq", "max_exp_avg_sq") and bool(
                            (value < 0).any()):
                        return f"a negative {name}"
                if self._moments_apart(moments):
                    return "a first moment larger than its second moment allows"
            return self._rate_problem()
        if key == "scheduler":
            return self._schedule_problem()
        if key == "average":
            expected = self.average.count_after(self.epoch)
            if self.average.count != expected:
                return (f"an average of {self.average.count} epochs, where {expected} of its "
                        f"tail are finished at epoch {self.epoch}")
        return None

    def _moments_apart(self, moments: dict) -> bool:
        """Whether Adam's moments of one parameter are no state its updates reach: from zero,
        m = (1-b1) sum b1^k g_k and v = (1-b2) sum b2^k g_k^2, so by Cauchy-Schwarz
        m^2 <= C v with C = (1-b1)^2 / ((1-b2) (1 - b1^2/b2)) (about 53 for the betas 0.9,
        0.999), whatever the gradients were."""
        m, v = moments.get("exp_avg"), moments.get("exp_avg_sq")
        if not (torch.is_tensor(m) and torch.is_tensor(v) and m.shape == v.shape):
            return False
        b1, b2 = self.opt.param_groups[0]["betas"]
        if not b1 * b1 < b2 < 1:
            return False
        bound = (1 - b1) ** 2 / ((1 - b2) * (1 - b1 * b1 / b2))
        m, v = m.double(), v.double()
        return bool((m * m > bound * (1 + 1e-3) * v + 1e-30).any())

    def _schedule_problem(self) -> str | None:
        now = self.sched.state_dict()
        last = now["last_epoch"]
        if {k: now[k] for k in self.schedule} != self.schedule or not all(
                type(now[k]) is int and now[k] >= 0 for k in ("last_epoch", "_step_count")):
            return "another schedule"
        first = self.epoch * self.steps_per_epoch  # steps of the finished epochs, and at most
        if not first <= last <= first + self.steps_per_epoch:  # the interrupted one's
            return (f"{last} steps, where epoch {self.epoch} of {self.steps_per_epoch} steps "
                    f"each is {first} to {first + self.steps_per_epoch}")
        return None

    def _rate_problem(self) -> str | None:
        """The optimiser (restored after the schedule) off the schedule: a learning rate
        other than the schedule's at its step, or a step count other than its."""
        last = self.sched.last_epoch
        gamma, size = self.schedule["gamma"], self.schedule["step_size"]
        for group, base in zip(self.opt.param_groups, self.schedule["base_lrs"]):
            rate = base * gamma ** (last // size)
            if not (type(group["lr"]) is float and abs(group["lr"] - rate) <= 1e-6 * rate):
                return (f"a learning rate of {group['lr']!r:.40}, where the schedule gives "
                        f"{rate:.6g} at step {last}")
            for param in group["params"]:
                step = self.opt.state.get(param, {}).get("step")
                if torch.is_tensor(step) and abs(float(step) - last) > 1:
                    return f"{float(step):.0f} optimiser steps, where the schedule took {last}"
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
