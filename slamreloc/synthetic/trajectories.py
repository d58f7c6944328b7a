"""Handheld-like camera paths inside the room: world_from_cam poses (metres, OpenCV camera).

Every path is an ellipse around the room centre (camera zone between the central table and the
wall-side objects of `room`), looking outwards at walls and objects 1-4 m away, with smooth random
wobble in position and orientation.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slamreloc.geometry import Rigid3, axis_angle_to_matrix, look_at

SEQUENCES = {"seq-01": "map", "seq-02": "query", "seq-03": "kidnap", "seq-04": "unlabelled"}


@dataclass(frozen=True)
class LoopSpec:
    """Ellipse semi-axes (m), height (m), start angle and turns, view offsets (degrees).

    Values given as (start, end) pairs blend smoothly along the path (used by 'unlabelled').
    """

    axes: tuple[tuple[float, float], tuple[float, float]]
    height: tuple[float, float]
    theta0: float
    turns: float
    yaw_deg: tuple[float, float]  # mean yaw offset from looking straight outwards
    yaw_swing_deg: float  # amplitude of a slow yaw oscillation on top
    pitch_deg: tuple[float, float]  # negative looks down
    speed_mod: float = 0.2  # relative speed variation along the path
    wobble_m: float = 0.02
    wobble_deg: float = 1.0


def _smooth_noise(rng: np.random.Generator, n: int, dims: int, sigma: float) -> np.ndarray:
    """(n, dims) Gaussian-smoothed white noise, unit standard deviation in expectation."""
    half = int(3 * sigma) + 1
    kernel = np.exp(-0.5 * (np.arange(-half, half + 1) / sigma) ** 2)
    white = rng.standard_normal((n + 2 * half, dims))
    out = np.stack([np.convolve(white[:, d], kernel, "valid") for d in range(dims)], 1)
    return out / np.sqrt(np.sum(kernel**2))


def loop_poses(rng: np.random.Generator, n: int, spec: LoopSpec) -> list[Rigid3]:
    """n world_from_cam poses along `spec`, wobble drawn from `rng`."""
    s = np.arange(n) / n if abs(spec.turns) == 1 else np.arange(n) / max(n - 1, 1)
    s = s + spec.speed_mod * np.sin(2 * np.pi * s) / (2 * np.pi)
    theta = spec.theta0 + 2 * np.pi * spec.turns * s
    w = 0.5 - 0.5 * np.cos(np.pi * s)  # 0 -> 1 smoothly along the path

    def blend(pair: tuple[float, float]) -> np.ndarray:
        return (1 - w) * pair[0] + w * pair[1]

    a, b = blend((spec.axes[0][0], spec.axes[1][0])), blend((spec.axes[0][1], spec.axes[1][1]))
    height = blend(spec.height) + 0.05 * np.sin(2 * theta + 1.0)
    pos_noise = spec.wobble_m * _smooth_noise(rng, n, 3, sigma=6.0)
    rot_noise = np.radians(spec.wobble_deg) * _smooth_noise(rng, n, 3, sigma=4.0)
    yaw = (np.arctan2(a * np.sin(theta), b * np.cos(theta))
           + np.radians(blend(spec.yaw_deg) + spec.yaw_swing_deg * np.sin(3 * theta + 0.7)))
    pitch = np.radians(blend(spec.pitch_deg))
    poses = []
    for i in range(n):
        eye = np.array([a[i] * np.cos(theta[i]), b[i] * np.sin(theta[i]), height[i]]) + pos_noise[i]
        view = np.array([np.cos(pitch[i]) * np.cos(yaw[i]), np.cos(pitch[i]) * np.sin(yaw[i]),
                         np.sin(pitch[i])])
        base = look_at(eye, eye + view)
        poses.append(Rigid3(base.rotation @ axis_angle_to_matrix(rot_noise[i]), eye))
    return poses


SPECS = {
    "seq-01": LoopSpec(((1.45, 1.05),) * 2, (1.5, 1.5), 0.0, 1, (0, 0), 10.0, (-10, -10)),
    "seq-02": LoopSpec(((1.25, 0.88),) * 2, (1.32, 1.32), 0.3, -1, (8, 8), 8.0, (-6, -6)),
    "seq-03": LoopSpec(((1.6, 1.2),) * 2, (1.42, 1.42), 2.0, 0.45, (-12, -12), 6.0, (-12, -12),
                       speed_mod=0.25, wobble_m=0.015),
    "seq-04": LoopSpec(((1.5, 1.1), (1.8, 1.3)), (1.55, 1.1), 4.0, 1, (0, 35), 6.0, (-10, -22)),
}


def make_trajectories(seed: int, counts: dict[str, int]) -> dict[str, list[Rigid3]]:
    """Poses of each sequence in `counts` (names as in SEQUENCES), deterministic per seed."""
    return {name: loop_poses(np.random.default_rng([seed, 100 + i]), counts[name], SPECS[name])
            for i, name in enumerate(SEQUENCES) if name in counts}
