"""Regions of the scene for the region-classification head: k-means of training points.

The points are world points in the regressor's normalised frame (any (N, 3) float tensor);
distances are in the points' units. Used when a map is trained (`set_clusters`) and when the
pseudo-label update moves regions onto a new area.
"""

from __future__ import annotations

import torch

POINT_BLOCK = 65536  # points per distance block (bounds the (block, K) distance matrix)


@torch.no_grad()
def nearest_centres(points: torch.Tensor, centres: torch.Tensor
                    ) -> tuple[torch.Tensor, torch.Tensor]:
    """(distance (N,), index (N,)) of each point's nearest centre (the first one on ties)."""
    dist, index = [], []
    for block in points.split(POINT_BLOCK):
        d, i = torch.cdist(block, centres).min(1)
        dist.append(d)
        index.append(i)
    return torch.cat(dist), torch.cat(index)


@torch.no_grad()
def kmeans(points: torch.Tensor, k: int, generator: torch.Generator,
           iterations: int = 20) -> torch.Tensor:
    """(k, 3) centres: Lloyd's iterations from k distinct random points (drawn with repeats
    when there are fewer than k points); an empty cluster keeps its centre."""
    n, dev = len(points), points.device
    start = (torch.randperm(n, generator=generator, device=dev)[:k] if n >= k else
             torch.randint(n, (k,), generator=generator, device=dev))
    centres = points[start].clone()
    for _ in range(iterations):
        assign = nearest_centres(points, centres)[1]
        count = torch.bincount(assign, minlength=k).float()
        total = torch.zeros_like(centres).index_add_(0, assign, points)
        centres[count > 0] = total[count > 0] / count[count > 0, None]
    return centres
