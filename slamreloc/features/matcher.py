"""Nearest-neighbour descriptor matching (dot products of unit descriptors, in torch)."""

from __future__ import annotations

import numpy as np
import torch


def _sq_dist_top2(query: torch.Tensor, db: torch.Tensor, chunk: int = 65536):
    """Squared L2 distances and indices of the 2 nearest db rows for each query row."""
    best_d = torch.full((len(query), 2), 4.0)
    best_i = torch.zeros((len(query), 2), dtype=torch.long)
    for start in range(0, len(db), chunk):
        sim = query @ db[start:start + chunk].T
        k = min(2, sim.shape[1])
        val, idx = sim.topk(k, dim=1)
        d = (2.0 - 2.0 * val).clamp_min(0)
        cand_d = torch.cat([best_d, d], 1)
        cand_i = torch.cat([best_i, idx + start], 1)
        order = cand_d.argsort(dim=1)[:, :2]
        best_d, best_i = cand_d.gather(1, order), cand_i.gather(1, order)
    return best_d, best_i


def top2(query: np.ndarray, db: np.ndarray | torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """(distances (N, 2) in descriptor L2 units, indices (N, 2)) of the two nearest db rows."""
    q = torch.as_tensor(query, dtype=torch.float32)
    d = db if isinstance(db, torch.Tensor) else torch.as_tensor(db, dtype=torch.float32)
    with torch.inference_mode():  # query blocks bound memory to ~1 GB of similarities
        parts = [_sq_dist_top2(q[s:s + 4096], d.float()) for s in range(0, len(q), 4096)]
    if not parts:
        return np.zeros((0, 2), np.float32), np.zeros((0, 2), np.int64)
    return (torch.cat([p[0] for p in parts]).sqrt().numpy(),
            torch.cat([p[1] for p in parts]).numpy())


def match_mutual(desc_a: np.ndarray, desc_b: np.ndarray, ratio: float = 0.8) -> np.ndarray:
    """(M, 2) index pairs (i in a, j in b): mutual nearest neighbours passing Lowe's ratio test."""
    if len(desc_a) < 2 or len(desc_b) < 2:
        return np.zeros((0, 2), np.int64)
    with torch.inference_mode():
        sim = torch.as_tensor(desc_a) @ torch.as_tensor(desc_b).T
        val_ab, idx_ab = sim.topk(2, dim=1)
        idx_ba = sim.argmax(dim=0)
    dist = (2.0 - 2.0 * val_ab).clamp_min(0).sqrt().numpy()
    idx_ab = idx_ab.numpy()
    i = np.arange(len(desc_a))
    keep = (idx_ba.numpy()[idx_ab[:, 0]] == i) & (dist[:, 0] < ratio * dist[:, 1])
    return np.stack([i[keep], idx_ab[keep, 0]], axis=1)
