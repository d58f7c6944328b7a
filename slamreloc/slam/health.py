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


@dataclass
class HealthReport:
    verdict: Health
    reason: str
    motion_m: float
    motion_deg: float


def check_health(step: OdometryStep, cam_prev_from_cam: Rigid3 | None,
                 config: HealthConfig = HealthConfig()) -> HealthReport:
    """Judge one odometry step; `cam_prev_from_cam` is the motion since the previous frame
    (None for the first frame of a track)."""
    if cam_prev_from_cam is None:
        return HealthReport(Health.OK, "first frame", 0.0, 0.0)
    dm = float(np.linalg.norm(cam_prev_from_cam.translation))
    dr = rotation_angle_deg(cam_prev_from_cam.rotation)
    fit = step.fitness
    checks = [
        (step.extra.get("n_points", step.n_points) < config.min_points and step.n_points > 0,
         Health.LOST, f"only {step.n_points} depth points"),
        (dm > config.lost_motion_m or dr > config.lost_motion_deg, Health.LOST,
         f"implausible motion {dm:.3f} m / {dr:.1f} deg in one frame"),
        (fit is not None and fit < config.lost_fitness, Health.LOST, f"fitness {fit}"),
        (dm > config.suspect_motion_m or dr > config.suspect_motion_deg, Health.SUSPECT,
         f"fast motion {dm:.3f} m / {dr:.1f} deg"),
        (fit is not None and fit < config.suspect_fitness, Health.SUSPECT, f"fitness {fit}"),
    ]
    for failed, verdict, reason in checks:
        if failed:
            return HealthReport(verdict, reason, dm, dr)
    return HealthReport(Health.OK, "", dm, dr)
