"""Regressor update on labelled + pseudo-labelled data: fine-tuning from the current weights.

The region head classifies a descriptor into one of K k-means regions of the training points.
Points of the new area lie far from every old region centre, so before fine-tuning some regions
are moved there: the least-used old regions (by the updated training set) are re-seeded by
k-means of the far points, and their rows of the output layer are reset. The input/output
normalisation stays as trained (the hidden layers' features keep their meaning); the samples
carry quality weights (pseudo-labels by their reprojection error). The training loop is the
core's (`train_regressor(..., fine_tune=True)`), with its precision choice.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass

import numpy as np
import torch

from slamreloc.regressor.model import SceneCoordinateRegressor
from slamreloc.regressor.regions import kmeans, nearest_centres
from slamreloc.regressor.train import TrainConfig, train_regressor


@dataclass(frozen=True)
class FinetuneConfig:
    """The fine-tuning recipe: the core's training loop with a shorter, gentler schedule."""

    epochs: int = 25
    lr: float = 1e-3
    lr_halvings: int = 3
    far_factor: float = 3.0  # a point is "new area" beyond this many mean offsets from a centre
    max_new_fraction: float = 0.5  # at most this share of the regions is moved
    seed: int = 0

    def to_dict(self) -> dict:
        return asdict(self)

    def train_config(self) -> TrainConfig:
        return TrainConfig(epochs=self.epochs, lr=self.lr, lr_halvings=self.lr_halvings,
                           seed=self.seed)


@torch.no_grad()
def extend_regions(model: SceneCoordinateRegressor, points_n: torch.Tensor,
                   config: FinetuneConfig, gen: torch.Generator) -> tuple[torch.Tensor, int]:
    """Move the least-used regions onto the new area; returns (cluster per point, n moved)."""
    centres = model.centres
    k = len(centres)

    dist, assign = nearest_centres(points_n, centres)
    far = dist > config.far_factor * model.offset_scale
    n_far = int(far.sum())
    n_move = 0
    if n_far >= 2:
        n_move = int(np.clip(round(k * n_far / len(points_n)), 1,
                             min(int(config.max_new_fraction * k), n_far)))
        use = torch.bincount(assign[~far], minlength=k)
        moved = torch.argsort(use.float() + torch.rand(k, generator=gen) * 0.1)[:n_move]
        centres[moved] = kmeans(points_n[far], n_move, gen)
        out = model.mlp[-1]
        bound = 1.0 / np.sqrt(out.in_features)
        out.weight[moved] = torch.empty(n_move, out.in_features).uniform_(-bound, bound,
                                                                          generator=gen)
        out.bias[moved] = out.bias[:k].mean()
        rows = (k + moved[:, None] * 3 + torch.arange(3)[None]).reshape(-1)
        out.weight[rows] = 0.0
        out.bias[rows] = 0.0
        dist, assign = nearest_centres(points_n, centres)
    return assign, n_move


def finetune_regressor(model: SceneCoordinateRegressor, descriptors: np.ndarray,
                       points: np.ndarray, weights: np.ndarray,
                       config: FinetuneConfig = FinetuneConfig(), device: str = "auto",
                       progress: bool = True) -> dict:
    """Continue training `model` (in place) on quality-weighted samples. Returns stats."""
    t0 = time.perf_counter()
    n_moved = 0
    if model.config.head == "clusters":
        model.cpu()
        y_n = (torch.as_tensor(points, dtype=torch.float32) - model.out_mean) / model.out_scale
        _, n_moved = extend_regions(model, y_n, config,
                                    torch.Generator().manual_seed(config.seed))
    stats = train_regressor(model, descriptors, points, config.train_config(), device,
                            progress, weights=weights, fine_tune=True)
    return {"mode": "finetune", **stats, "regions_moved": n_moved,
            "time_s": time.perf_counter() - t0}
