"""TUM trajectory files (`timestamp tx ty tz qx qy qz qw`, camera-to-world, metres), as evo
reads them: a numeric first column, `#` comment lines."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from slamreloc.errors import InputError
from slamreloc.geometry import Rigid3, read_tum_trajectory


def read_tum(path: Path) -> tuple[np.ndarray, list[Rigid3]]:
    """(timestamps (N,), world_from_cam poses); InputError on a malformed line."""
    rows = read_tum_trajectory(path, numeric_stamps=True)
    if not rows:  # (a session that never anchored writes one: the file is fine, not for this)
        raise InputError(f"{path}: no poses in the trajectory file, and odometry needs the "
                         "poses of the frames it tracks")
    return np.array([float(stamp) for stamp, _ in rows]), [pose for _, pose in rows]
