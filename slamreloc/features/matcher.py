"""Nearest-neighbour descriptor matching (dot products of unit descriptors, in torch).

One function, `match_descriptors`, serves every matcher in the package: the matching
localizer (ratio test or one 3D point, no mutual check), the mapping labels' pairwise matches
and the pseudo-label registration (mutual nearest neighbours, with or without the 3D-point
exception). Distances are L2 between unit descriptors, sqrt(2 - 2 cos).
"""

from __future__ import annotations

import numpy as np
import torch

QUERY_BLOCK = 4096  # query rows per block
DB_CHUNK = 32768  # database rows per block: <= 512 MB of float32 similarities at a time
# The product's rounding depends on the block's shape (BLAS picks its kernel by size), so a
# caller whose results must stay bit-for-bit as they were keeps its block size: the matching
# localizer has always multiplied 65536 database rows at a time.
LOCALIZER_DB_CHUNK = 65536


def _nearest_two(query: torch.Tensor, db: torch.Tensor, mutual: bool, db_chunk: int):
    """(similarities (N, 2), indices (N, 2)) of the two most similar db rows per query row,
    most similar first, and with `mutual` each db row's most similar query row (M,) (the
    first one on ties), else None."""
    n, m = len(query), len(db)
    best_v = torch.full((n, 2), -2.0)
    best_i = torch.zeros((n, 2), dtype=torch.long)
    col_v = torch.full((m,), -3.0) if mutual else None
    col_i = torch.zeros(m, dtype=torch.long) if mutual else None
    for qs in range(0, n, QUERY_BLOCK):
        q = query[qs:qs + QUERY_BLOCK]
        for s in range(0, m, db_chunk):
            sim = q @ db[s:s + db_chunk].T
            if mutual:
                v, i = sim.max(0)
                better = v > col_v[s:s + len(v)]  # strict: an earlier query block wins ties
                col_v[s:s + len(v)] = torch.where(better, v, col_v[s:s + len(v)])
                col_i[s:s + len(v)] = torch.where(better, i + qs, col_i[s:s + len(v)])
            val, idx = sim.topk(min(2, sim.shape[1]), dim=1)
            cand_v = torch.cat([best_v[qs:qs + len(q)], val], 1)
            cand_i = torch.cat([best_i[qs:qs + len(q)], idx + s], 1)
            order = cand_v.argsort(dim=1, descending=True, stable=True)[:, :2]
            best_v[qs:qs + len(q)] = cand_v.gather(1, order)
            best_i[qs:qs + len(q)] = cand_i.gather(1, order)
    return best_v, best_i, col_i


def match_descriptors(query: np.ndarray, db: np.ndarray | torch.Tensor, ratio: float,
                      mutual: bool = True, db_points: np.ndarray | None = None,
                      same_point_m: float = 0.0, db_chunk: int | None = None) -> np.ndarray:
    """(M, 2) index pairs (i in query, j in db), by ascending i: each query descriptor's
    nearest db descriptor j, kept when it passes Lowe's ratio test (distance to j below
    `ratio` times the distance to the second nearest) or, given `db_points` ((len(db), 3),
    metres), when the two nearest db entries are one 3D point (closer than `same_point_m`);
    with `mutual`, only when i is also j's nearest query descriptor. Empty when either side has
    fewer than 2 descriptors. Descriptors: unit rows, float32. `db_chunk`: database rows per
    matrix product (default DB_CHUNK; see LOCALIZER_DB_CHUNK)."""
    n, m = len(query), len(db)
    if n < 2 or m < 2:
        return np.zeros((0, 2), np.int64)
    q = torch.as_tensor(query, dtype=torch.float32)
    d = (db if isinstance(db, torch.Tensor) else torch.as_tensor(db)).float()
    with torch.inference_mode():
        best_v, best_i, col_i = _nearest_two(q, d, mutual, db_chunk or DB_CHUNK)
    dist = (2.0 - 2.0 * best_v).clamp_min(0).sqrt().numpy()
    idx = best_i.numpy()
    keep = dist[:, 0] < ratio * dist[:, 1]
    if db_points is not None:
        keep |= np.linalg.norm(db_points[idx[:, 0]] - db_points[idx[:, 1]], axis=1) < same_point_m
    qi = np.arange(n)
    if mutual:
        keep &= col_i.numpy()[idx[:, 0]] == qi
    return np.stack([qi[keep], idx[keep, 0]], axis=1)
