"""Training the regressor on labelled descriptors (L2 distance loss, metres)."""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
import torch
from torch import nn

from slamreloc.progress import track
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
    bf16: bool = True  # mixed precision (CPU AMX / CUDA tensor cores)
    seed: int = 0

    def to_dict(self) -> dict:
        return asdict(self)


def resolve_device(device: str) -> torch.device:
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if device == "cuda" and not torch.cuda.is_available():
        raise ValueError("--device cuda asked for, but torch sees no CUDA device")
    return torch.device(device)


def train_regressor(model: SceneCoordinateRegressor, descriptors: np.ndarray, points: np.ndarray,
                    config: TrainConfig = TrainConfig(), device: str = "auto",
                    progress: bool = True) -> dict:
    """Fit `model` to (N, D) descriptors -> (N, 3) world points. Returns training stats."""
    dev = resolve_device(device)
    torch.manual_seed(config.seed)
    x = torch.as_tensor(descriptors, dtype=torch.float32, device=dev)
    y = torch.as_tensor(points, dtype=torch.float32, device=dev)
    model.to(dev).set_normalisation(x, y)
    x = model.normalise_input(x)
    y_n = (y - model.out_mean) / model.out_scale
    gen = torch.Generator(device=dev).manual_seed(config.seed)
    if model.config.prototype_init:
        model.init_prototypes(x, gen)
    cluster = model.set_clusters(y_n, gen) if model.config.head == "clusters" else None
    opt = torch.optim.AdamW(model.parameters(), lr=config.lr, betas=config.betas,
                            weight_decay=config.weight_decay)
    steps_per_epoch = max(1, len(x) // config.batch_size)
    total = config.epochs * steps_per_epoch
    sched = torch.optim.lr_scheduler.StepLR(
        opt, step_size=max(1, total // config.lr_halvings), gamma=0.5)
    model.train()
    losses = []
    for epoch in track(range(config.epochs), "training regressor", enabled=progress):
        noise = config.noise * (1 - epoch / config.epochs if config.noise_anneal else 1.0)
        perm = torch.randperm(len(x), device=dev, generator=gen)
        epoch_loss = torch.zeros((), device=dev)
        for s in range(steps_per_epoch):
            idx = perm[s * config.batch_size:(s + 1) * config.batch_size]
            xb = x[idx]
            if noise > 0:
                xb = xb + noise * torch.randn(xb.shape, device=dev, generator=gen)
            if config.input_dropout > 0:
                keep = torch.rand(xb.shape, device=dev, generator=gen) > config.input_dropout
                xb = xb * keep / (1 - config.input_dropout)
            with torch.autocast(dev.type, dtype=torch.bfloat16, enabled=config.bf16):
                hidden = model.hidden(xb)
            target = None if cluster is None else cluster[idx]
            pred, logits = model.head_outputs(hidden, target)
            dist = (pred - y_n[idx]).norm(dim=1).mean()
            loss = dist
            if logits is not None:  # region classification + offset within the true region
                loss = dist / model.offset_scale + nn.functional.cross_entropy(logits, target)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            sched.step()
            epoch_loss += dist.detach()
        losses.append(float(epoch_loss) / steps_per_epoch * float(model.out_scale))
    model.eval().cpu()
    return {"final_loss_m": losses[-1] if losses else None, "epochs": config.epochs,
            "n_samples": len(x), "device": dev.type}
