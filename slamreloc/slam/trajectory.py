"""TUM trajectory files (`timestamp tx ty tz qx qy qz qw`, camera-to-world, metres), as evo
reads them: a numeric first column, `#` comment lines."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from slamreloc.errors import InputError
from slamreloc.fileio import atomic_file
from slamreloc.geometry import Rigid3, read_tum_trajectory, tum_line


def write_tum(path: Path, timestamps: list[float], world_from_cam: list[Rigid3],
              comments: list[str] = ()) -> None:
    lines = [f"# {c}\n" for c in comments]
    lines += [tum_line(f"{t:.6f}", p) + "\n" for t, p in zip(timestamps, world_from_cam)]
    with atomic_file(path) as tmp:
        tmp.write_text("".join(lines))


def read_tum(path: Path) -> tuple[np.ndarray, list[Rigid3]]:
    """(timestamps (N,), world_from_cam poses); InputError on a malformed line."""
    rows = read_tum_trajectory(path, numeric_stamps=True)
    if not rows:
        raise InputError(f"{path}: no poses in the trajectory file")
    return np.array([float(stamp) for stamp, _ in rows]), [pose for _, pose in rows]


def associate(stamps: np.ndarray, queries: np.ndarray, max_dt: float = 0.01) -> np.ndarray:
    """Index into `stamps` of the nearest stamp for each query; -1 beyond `max_dt` seconds."""
    order = np.argsort(stamps)
    s = stamps[order]
    pos = np.clip(np.searchsorted(s, queries), 1, max(len(s) - 1, 1))
    left = np.clip(pos - 1, 0, len(s) - 1)
    pick = np.where(np.abs(s[left] - queries) <= np.abs(s[pos] - queries), left, pos)
    return np.where(np.abs(s[pick] - queries) <= max_dt, order[pick], -1)
