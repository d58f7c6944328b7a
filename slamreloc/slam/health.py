"""Tracking-health checks on odometry output: the backend decides loss itself.

Three verdicts: OK; SUSPECT (relocalize this frame to check the track); LOST (the track is not
trusted any more: odometry restarts and relocalization must re-anchor it).
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum

import numpy as np

from slamreloc.geometry import Rigid3, rotation_angle_deg
from slamreloc.slam.odometry import OdometryStep


class Health(str, Enum):
    OK = "ok"
    SUSPECT = "suspect"
    LOST = "lost"


@dataclass(frozen=True)
class HealthConfig:
    """Per-frame motion limits (metres, degrees per frame at the sensor rate; 0.1 m/frame is
    3 m/s at 30 Hz) and fitness limits (share of points on the model after registration)."""

    lost_motion_m: float = 0.10
    lost_motion_deg: float = 10.0
    suspect_motion_m: float = 0.04
    suspect_motion_deg: float = 4.0
    lost_fitness: float = 0.6
    suspect_fitness: float = 0.8
    min_points: int = 200  # fewer depth points than this: nothing to register
    # a camera that moves fast all the time raises the motion limits to these multiples of
    # its median recent motion (per frame)
    lost_motion_ratio: float = 5.0
    suspect_motion_ratio: float = 2.5


@dataclass
class HealthReport:
    verdict: Health
    reason: str
    motion_m: float
    motion_deg: float


def check_health(step: OdometryStep, cam_prev_from_cam: Rigid3 | None,
                 config: HealthConfig = HealthConfig(),
                 recent: tuple[float, float] = (0.0, 0.0)) -> HealthReport:
    """Judge one odometry step; `cam_prev_from_cam` is the motion since the previous frame
    (None for the first frame of a track); `recent` the median motion per frame over the last
    frames (metres, degrees)."""
    if cam_prev_from_cam is None:
        return HealthReport(Health.OK, "first frame", 0.0, 0.0)
    dm = float(np.linalg.norm(cam_prev_from_cam.translation))
    dr = rotation_angle_deg(cam_prev_from_cam.rotation)
    fit = step.fitness
    fit_text = "n/a" if fit is None else f"{fit:.2f}"
    c = config
    lost_m = max(c.lost_motion_m, c.lost_motion_ratio * recent[0])
    lost_deg = max(c.lost_motion_deg, c.lost_motion_ratio * recent[1])
    sus_m = max(c.suspect_motion_m, c.suspect_motion_ratio * recent[0])
    sus_deg = max(c.suspect_motion_deg, c.suspect_motion_ratio * recent[1])
    checks = [
        (0 < step.n_points < c.min_points, Health.LOST, f"only {step.n_points} depth points"),
        (dm > lost_m or dr > lost_deg, Health.LOST,
         f"implausible motion {dm:.3f} m / {dr:.1f} deg in one frame"),
        (fit is not None and fit < c.lost_fitness, Health.LOST, f"fitness {fit_text}"),
        (dm > sus_m or dr > sus_deg, Health.SUSPECT, f"fast motion {dm:.3f} m / {dr:.1f} deg"),
        (fit is not None and fit < c.suspect_fitness, Health.SUSPECT, f"fitness {fit_text}"),
    ]
    for failed, verdict, reason in checks:
        if failed:
            return HealthReport(verdict, reason, dm, dr)
    return HealthReport(Health.OK, "", dm, dr)
