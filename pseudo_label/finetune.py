"""Regressor update on labelled + pseudo-labelled data: fine-tuning from the current weights.

The region head classifies a descriptor into one of K k-means regions of the training points.
Points of the new area lie far from every old region centre, so before fine-tuning some regions
are moved there: the least-used old regions (by the updated training set) are re-seeded by
k-means of the far points, and their rows of the output layer are reset. The input/output
normalisation stays as trained (the hidden layers' features keep their meaning); the samples
carry quality weights (pseudo-labels by their reprojection error).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass

import numpy as np
import torch
from torch import nn

from slamreloc.progress import track
from slamreloc.regressor.model import SceneCoordinateRegressor
from slamreloc.regressor.train import resolve_device


@dataclass(frozen=True)
class FinetuneConfig:
    epochs: int = 25
    batch_size: int = 1024
    lr: float = 1e-3
    weight_decay: float = 5e-4
    lr_halvings: int = 3
    noise: float = 0.2
    input_dropout: float = 0.2
    far_factor: float = 3.0  # a point is "new area" beyond this many mean offsets from a centre
    max_new_fraction: float = 0.5  # at most this share of the regions is moved
    seed: int = 0

    def to_dict(self) -> dict:
        return asdict(self)


def _bf16_ok(dev: torch.device) -> bool:
    if dev.type == "cuda":
        return True
    try:
        with open("/proc/cpuinfo") as f:
            flags = next((line for line in f if line.startswith("flags")), "")
    except OSError:
        return False
    return "amx" in flags  # native bf16 matmuls; elsewhere bf16 is slower than fp32


def _kmeans(points: torch.Tensor, k: int, gen: torch.Generator, iterations: int = 20):
    start = torch.randperm(len(points), generator=gen)[:k]
    centres = points[start].clone()
    for _ in range(iterations):
        assign = torch.cdist(points, centres).argmin(1)
        count = torch.bincount(assign, minlength=k).float()
        total = torch.zeros_like(centres).index_add_(0, assign, points)
        centres[count > 0] = total[count > 0] / count[count > 0, None]
    return centres


@torch.no_grad()
def extend_regions(model: SceneCoordinateRegressor, points_n: torch.Tensor,
                   config: FinetuneConfig, gen: torch.Generator) -> tuple[torch.Tensor, int]:
    """Move the least-used regions onto the new area; returns (cluster per point, n moved)."""
    centres = model.centres
    k = len(centres)

    def nearest():
        return _nearest(points_n, centres)

    dist, assign = nearest()
    far = dist > config.far_factor * model.offset_scale
    n_far = int(far.sum())
    n_move = 0
    if n_far >= 2:
        n_move = int(np.clip(round(k * n_far / len(points_n)), 1,
                             min(int(config.max_new_fraction * k), n_far)))
        use = torch.bincount(assign[~far], minlength=k)
        moved = torch.argsort(use.float() + torch.rand(k, generator=gen) * 0.1)[:n_move]
        centres[moved] = _kmeans(points_n[far], n_move, gen)
        out = model.mlp[-1]
        bound = 1.0 / np.sqrt(out.in_features)
        out.weight[moved] = torch.empty(n_move, out.in_features).uniform_(-bound, bound,
                                                                          generator=gen)
        out.bias[moved] = out.bias[:k].mean()
        rows = (k + moved[:, None] * 3 + torch.arange(3)[None]).reshape(-1)
        out.weight[rows] = 0.0
        out.bias[rows] = 0.0
        dist, assign = nearest()
    return assign, n_move


def _nearest(points: torch.Tensor, centres: torch.Tensor):
    d, a = [], []
    for chunk in points.split(65536):
        v, i = torch.cdist(chunk, centres).min(1)
        d.append(v)
        a.append(i)
    return torch.cat(d), torch.cat(a)


def finetune_regressor(model: SceneCoordinateRegressor, descriptors: np.ndarray,
                       points: np.ndarray, weights: np.ndarray,
                       config: FinetuneConfig = FinetuneConfig(), device: str = "auto",
                       progress: bool = True) -> dict:
    """Continue training `model` (in place) on weighted samples. Returns stats."""
    t0 = time.perf_counter()
    dev = resolve_device(device)
    torch.manual_seed(config.seed)
    gen_cpu = torch.Generator().manual_seed(config.seed)
    model.cpu()
    x = model.normalise_input(torch.as_tensor(descriptors, dtype=torch.float32))
    y_n = (torch.as_tensor(points, dtype=torch.float32) - model.out_mean) / model.out_scale
    w = torch.as_tensor(weights, dtype=torch.float32)
    cluster, n_moved = (extend_regions(model, y_n, config, gen_cpu)
                        if model.config.head == "clusters" else (None, 0))
    model.to(dev)
    x, y_n, w = x.to(dev), y_n.to(dev), w.to(dev)
    cluster = None if cluster is None else cluster.to(dev)
    gen = torch.Generator(device=dev).manual_seed(config.seed)
    opt = torch.optim.AdamW(model.parameters(), lr=config.lr, weight_decay=config.weight_decay)
    steps = max(1, len(x) // config.batch_size)
    total = config.epochs * steps
    sched = torch.optim.lr_scheduler.StepLR(opt, step_size=max(1, total // config.lr_halvings),
                                            gamma=0.5)
    bf16 = _bf16_ok(dev)
    model.train()
    losses = []
    for _ in track(range(config.epochs), "fine-tuning regressor", enabled=progress):
        perm = torch.randperm(len(x), device=dev, generator=gen)
        epoch_loss = torch.zeros((), device=dev)
        for s in range(steps):
            idx = perm[s * config.batch_size:(s + 1) * config.batch_size]
            xb = x[idx]
            if config.noise > 0:
                xb = xb + config.noise * torch.randn(xb.shape, device=dev, generator=gen)
            if config.input_dropout > 0:
                keep = torch.rand(xb.shape, device=dev, generator=gen) > config.input_dropout
                xb = xb * keep / (1 - config.input_dropout)
            with torch.autocast(dev.type, dtype=torch.bfloat16, enabled=bf16):
                hidden = model.hidden(xb)
            target = None if cluster is None else cluster[idx]
            pred, logits = model.head_outputs(hidden, target)
            wb = w[idx]
            dist = (pred - y_n[idx]).norm(dim=1)
            if logits is not None:
                per = dist / model.offset_scale + nn.functional.cross_entropy(
                    logits, target, reduction="none")
            else:
                per = dist
            loss = (per * wb).sum() / wb.sum().clamp_min(1e-6)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            sched.step()
            epoch_loss += dist.mean().detach()
        losses.append(float(epoch_loss) / steps * float(model.out_scale))
    model.eval().cpu()
    return {"mode": "finetune", "final_loss_m": losses[-1] if losses else None,
            "epochs": config.epochs, "n_samples": len(x), "regions_moved": n_moved,
            "device": dev.type, "bf16": bf16, "time_s": time.perf_counter() - t0}
