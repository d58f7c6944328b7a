"""Training the regressor on labelled descriptors (L2 distance loss, metres)."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from slamreloc.runtime.precision import autocast, bf16_support, resolve_precision
from slamreloc.errors import Diverged, Interrupted
from slamreloc.io.outputs import signals_held
from slamreloc.runtime.progress import console, track
from slamreloc.regressor.checkpoint import (fingerprint, load_checkpoint, restore_checkpoint,
                                            save_checkpoint)
from slamreloc.regressor.model import SceneCoordinateRegressor


@dataclass(frozen=True)
class TrainConfig:
    epochs: int = 100
    batch_size: int = 1024
    lr: float = 2e-3
    weight_decay: float = 5e-4
    betas: tuple[float, float] = (0.9, 0.999)
    lr_halvings: int = 5  # the paper halves the lr every fifth of training
    # Gaussian noise on standardised inputs (fraction of each dim's std) and input dropout:
    # robustness to the descriptor changes of new views (optionally decayed to zero over
    # training with noise_anneal)
    noise: float = 0.2
    noise_anneal: bool = False
    input_dropout: float = 0.2
    # Weight averaging (SWA, Izmailov et al. 2018): the final weights are the mean of the
    # weights at the end of each epoch in the last `average_tail` fraction of training (0: the
    # last epoch's weights). With lr_halvings=5, 0.2 averages the lowest-lr stage.
    average_tail: float = 0.0
    precision: str = "auto"  # auto | fp32 | bf16 (slamreloc.runtime.precision: bf16 where native)
    seed: int = 0
    checkpoint_every_s: float = 30.0  # training state saved this often (when a path is given)

    def to_dict(self) -> dict:
        return asdict(self)


def resolve_device(device: str) -> torch.device:
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if device == "cuda" and not torch.cuda.is_available():
        raise ValueError("`device` cuda asked for, but torch sees no CUDA device")
    return torch.device(device)


def train_regressor(model: SceneCoordinateRegressor, descriptors: np.ndarray, points: np.ndarray,
                    config: TrainConfig = TrainConfig(), device: str = "auto",
                    progress: bool = True, checkpoint: Path | None = None,
                    resume: bool = False, weights: np.ndarray | None = None,
                    fine_tune: bool = False,
                    on_epoch_end: Callable[[int, float], None] | None = None,
                    on_step: Callable[[], None] | None = None,
                    settings: dict[str, str] | None = None) -> dict:
    """Fit `model` to (N, D) descriptors -> (N, 3) world points (metres). Returns training stats.

    checkpoint: a file to save training state to every `config.checkpoint_every_s` seconds
    and on Ctrl-C (which then raises `Interrupted`); resume: continue from it. settings: the
    run's settings (`checkpoint.run_settings`), kept in the checkpoint so that a resumed run
    is checked against them before its work (`checkpoint.check_settings`).
    weights: per-sample loss weights (label quality); fine_tune: continue from the model's
    weights, normalisation and regions instead of initialising them from the data.
    on_epoch_end(epoch, loss_m): called after each epoch (0-based) with its mean training
    distance (metres), before any weight averaging is applied to the model. on_step(): called
    after each optimiser step (a caller that must end training within a step raises there).
    Diverged where an epoch's loss is no longer a finite number."""
    t_cpu = time.process_time()
    dev = resolve_device(device)
    precision = resolve_precision(config.precision, dev.type)
    fp = fingerprint(descriptors, points, {**config.to_dict(), "precision": None,
                                           "checkpoint_every_s": None,
                                           "weighted": weights is not None,
                                           "fine_tune": fine_tune,
                                           "model": model.config.to_dict()})
    state = load_checkpoint(checkpoint, fp) if resume and checkpoint else None
    torch.manual_seed(config.seed)
    x = torch.as_tensor(descriptors, dtype=torch.float32, device=dev)
    y = torch.as_tensor(points, dtype=torch.float32, device=dev)
    w = (torch.ones(len(x), device=dev) if weights is None else
         torch.as_tensor(weights, dtype=torch.float32, device=dev))
    model.to(dev).requires_grad_(True)  # a model published for inference is frozen
    if not fine_tune:
        model.set_normalisation(x, y)
    x = model.normalise_input(x)
    y_n = (y - model.out_mean) / model.out_scale
    gen = torch.Generator(device=dev).manual_seed(config.seed)
    if state is None and not fine_tune:
        model.reset_parameters(gen)
        if model.config.prototype_init:
            model.init_prototypes(x, gen)
    cluster = None
    if model.config.head == "clusters" and state is None:
        cluster = model.assign_clusters(y_n) if fine_tune else model.set_clusters(y_n, gen)
    # fused: one kernel for every parameter's update instead of a few per tensor (2-core EPYC,
    # 3 epochs of 20k rows: 2.48 s against 2.78 with AVX512-BF16, 3.69 against 3.89 as
    # AVX2-only; the same losses); on a GPU it saves launches of a Python-bound loop
    opt = torch.optim.AdamW(model.parameters(), lr=config.lr, betas=config.betas,
                            weight_decay=config.weight_decay,
                            fused=dev.type in ("cpu", "cuda"))
    steps_per_epoch = max(1, len(x) // config.batch_size)
    sched = torch.optim.lr_scheduler.StepLR(
        opt, step_size=max(1, config.epochs * steps_per_epoch // config.lr_halvings), gamma=0.5)
    start, losses = 0, []
    average = WeightAverage(model, config.epochs, config.average_tail)
    if state is not None:
        start, losses = restore_checkpoint(checkpoint, state, config.epochs, steps_per_epoch,
                                           model, opt, sched, gen, average)
        if model.config.head == "clusters":
            cluster = model.assign_clusters(y_n)
        if progress:
            console.print(f"resuming training at epoch {start + 1}/{config.epochs}")
    model.train()
    if progress:  # printed once training state exists: Ctrl-C from here on is resumable
        console.print(f"training on {dev.type} in {precision} ({bf16_support(dev.type)[1]})")
    last_save = time.monotonic()
    epoch = start
    try:
        for epoch in track(range(start, config.epochs), "training regressor",
                           total=config.epochs - start, enabled=progress):
            noise = config.noise * (1 - epoch / config.epochs if config.noise_anneal else 1.0)
            perm = torch.randperm(len(x), device=dev, generator=gen)
            epoch_loss = torch.zeros((), device=dev)
            for s in range(steps_per_epoch):
                idx = perm[s * config.batch_size:(s + 1) * config.batch_size]
                dist = _step(model, opt, x[idx], y_n[idx], w[idx],
                             None if cluster is None else cluster[idx], noise, config, gen,
                             precision)
                sched.step()
                epoch_loss += dist
                if on_step is not None:
                    on_step()
            loss = float(epoch_loss) / steps_per_epoch * float(model.out_scale)
            if not np.isfinite(loss):
                raise Diverged(_divergence(epoch, config.epochs, checkpoint if state else None))
            with signals_held():  # an epoch is finished with its loss and average, or not
                losses.append(loss)
                average.update(model, epoch)
            if on_epoch_end is not None:
                on_epoch_end(epoch, losses[-1])
            if checkpoint and time.monotonic() - last_save > config.checkpoint_every_s:
                save_checkpoint(checkpoint, fp, epoch + 1, losses, model, opt, sched, gen,
                                average, settings)
                last_save = time.monotonic()
    except KeyboardInterrupt:
        if not checkpoint:
            raise
        # the epochs finished are those with a loss; an interrupted one is redone from the
        # state it had reached
        save_checkpoint(checkpoint, fp, len(losses), losses, model, opt, sched, gen, average,
                        settings)
        raise Interrupted(
            f"{checkpoint}: training interrupted at epoch {len(losses) + 1}/{config.epochs}; its "
            "state is saved there: run the same command with `resume` to continue") from None
    averaged = average.copy_to(model)
    model.eval().cpu()
    return {"final_loss_m": losses[-1] if losses else None, "epochs": config.epochs,
            "averaged_epochs": averaged,
            "resumed_at_epoch": start if state is not None else None,
            "n_samples": len(x), "device": dev.type, "precision": precision,
            "cpu_s": time.process_time() - t_cpu}  # CPU time of this process (all threads)


def _divergence(epoch: int, epochs: int, resumed_from: str | Path | None) -> str:
    """Why training stopped at 0-based `epoch`: its loss is no longer a finite number; after a
    resume, the checkpoint's state is the cause (no training from the start reaches it)."""
    if resumed_from is not None:
        return (f"{resumed_from}: training resumed from this checkpoint diverged at epoch "
                f"{epoch + 1}/{epochs} (its loss is no longer a finite number): its state is "
                "not one training reaches; run without `resume` to start anew")
    return (f"training diverged at epoch {epoch + 1}/{epochs}: its loss is no longer a finite "
            "number (lower `lr`, or check the labels)")


class WeightAverage:
    """Running mean of a model's parameters after each epoch of the last `tail` fraction of
    `epochs` (TrainConfig.average_tail)."""

    def __init__(self, model: nn.Module, epochs: int, tail: float) -> None:
        self.first_epoch = epochs - round(tail * epochs)  # 0-based; == epochs: none
        self.count = 0
        self.sums = {name: torch.zeros_like(p, dtype=torch.float32)
                     for name, p in model.named_parameters()}

    @torch.no_grad()
    def update(self, model: nn.Module, epoch: int) -> None:
        """Add the weights after 0-based `epoch` if it is in the tail."""
        if epoch < self.first_epoch:
            return
        for name, p in model.named_parameters():
            self.sums[name] += p.float()
        self.count += 1

    @torch.no_grad()
    def copy_to(self, model: nn.Module) -> int:
        """Set the model's parameters to the mean (if any snapshot was taken); returns the
        number of snapshots averaged."""
        if self.count:
            for name, p in model.named_parameters():
                p.copy_(self.sums[name] / self.count)
        return self.count

    def count_after(self, epochs_done: int) -> int:
        """How many snapshots the average holds once `epochs_done` epochs are finished."""
        return max(0, epochs_done - self.first_epoch)

    def state_dict(self) -> dict:
        return {"count": self.count, "sums": self.sums}

    def load_state_dict(self, state: dict) -> None:
        """ValueError unless `state` holds a whole count and a finite float32 sum of the
        shape of each of the model's parameters (what `state_dict` gave)."""
        count, sums = state["count"], state["sums"]
        if type(count) is not int or count < 0 or not isinstance(sums, dict) or (
                set(sums) != set(self.sums)):
            raise ValueError("not a weight average of this model")
        for name, t in sums.items():
            if (not torch.is_tensor(t) or t.shape != self.sums[name].shape
                    or t.dtype != torch.float32 or not bool(torch.isfinite(t).all())):
                raise ValueError(f"weight average of {name} is not of its parameter's shape")
        self.count = count
        self.sums = {name: t.clone() for name, t in sums.items()}


def _step(model, opt, xb, yb, wb, target, noise, config, gen, precision) -> torch.Tensor:
    """One optimisation step on a batch (augmented here) with per-sample weights `wb`; returns
    the mean distance (detached, normalised frame)."""
    dev = xb.device
    if noise > 0:
        xb = xb + noise * torch.randn(xb.shape, device=dev, generator=gen)
    if config.input_dropout > 0:
        keep = torch.rand(xb.shape, device=dev, generator=gen) > config.input_dropout
        xb = xb * keep / (1 - config.input_dropout)
    with autocast(dev.type, precision):
        hidden = model.hidden(xb)
    pred, logits = model.head_outputs(hidden, target)
    dist = (pred - yb).norm(dim=1)
    per = dist
    if logits is not None:  # region classification + offset within the true region
        per = dist / model.offset_scale + nn.functional.cross_entropy(logits, target,
                                                                       reduction="none")
    loss = (per * wb).sum() / wb.sum().clamp_min(1e-6)
    opt.zero_grad(set_to_none=True)
    loss.backward()
    opt.step()
    return dist.mean().detach()
