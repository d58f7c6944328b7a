"""Room geometry: axis-aligned boxes with one procedural texture per planar face.

World frame: metres, z up, floor at z = 0, room centred on x = y = 0. The layout keeps a
free zone for cameras (see `trajectories`): wall-side objects stay within `WALL_BAND` of the
walls and the central table inside `CENTRE_HALF`; nothing else stands in the room.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slamreloc.synthetic.textures import make_texture

HALF = np.array([3.0, 2.5])  # room half-extent in x, y (6 m x 5 m)
HEIGHT = 2.8
WALL_BAND = 0.5  # wall-side objects are at most this deep
CENTRE_HALF = np.array([0.45, 0.35])  # central table footprint half-size
TEXEL_M = 0.005
LIGHT = np.array([0.35, -0.55, 0.75]) / np.linalg.norm([0.35, -0.55, 0.75])


@dataclass(frozen=True)
class Face:
    """Rectangle origin + s*axis_u + t*axis_v, s in [0, size[0]], t in [0, size[1]] metres."""

    origin: np.ndarray
    axis_u: np.ndarray
    axis_v: np.ndarray
    size: tuple[float, float]
    normal: np.ndarray  # unit, pointing to the side cameras see
    texture: np.ndarray  # (H, W, 3) uint8; texel (i, j) centre at s = j * TEXEL_M, t = i * TEXEL_M


@dataclass(frozen=True)
class Room:
    faces: list[Face]
    boxes: list[tuple[np.ndarray, np.ndarray]]  # object (lo, hi) corners, metres


def _box_faces(lo: np.ndarray, hi: np.ndarray, inward: bool, skip_bottom: bool):
    """Yield (origin, u, v, size, normal) per face of box [lo, hi]; u x v = -normal, so textures
    read upright (v down on vertical faces) when seen from the front."""
    ext = hi - lo
    for axis in range(3):
        for side in (0, 1):
            if skip_bottom and axis == 2 and side == 0:
                continue
            centre = (lo + hi) / 2
            centre[axis] = hi[axis] if side else lo[axis]
            normal = np.zeros(3)
            normal[axis] = (1.0 if side else -1.0) * (-1.0 if inward else 1.0)
            u = np.eye(3)[0] if axis == 2 else np.cross([0.0, 0.0, -1.0], -normal)
            v = np.cross(-normal, u)
            size = (float(abs(ext @ u)), float(abs(ext @ v)))
            yield centre - size[0] / 2 * u - size[1] / 2 * v, u, v, size, normal


def _objects(rng: np.random.Generator) -> list[tuple[np.ndarray, np.ndarray]]:
    """Boxes standing on the floor: 1-2 per wall, a corner box, and a central table."""
    boxes = []
    for wall in range(4):
        axis, sign = wall % 2, (1.0 if wall < 2 else -1.0)  # axis 0: walls x = +-3
        along = 1 - axis
        lim = HALF[along] - WALL_BAND - 0.35
        n = int(rng.integers(1, 3))
        edges = np.sort(rng.uniform(-lim, lim, 2 * n))
        for i in range(n):
            a0 = min(edges[2 * i], lim - 0.4)
            a1 = max(edges[2 * i + 1], a0 + 0.4)
            depth = rng.uniform(0.3, WALL_BAND)
            height = rng.choice([rng.uniform(0.3, 0.6), rng.uniform(0.7, 1.0),
                                 rng.uniform(1.4, 2.0)])  # box, table/sideboard, cabinet
            lo, hi = np.zeros(3), np.array([0.0, 0.0, height])
            lo[along], hi[along] = a0, min(a1, lim)
            wall_pos = sign * HALF[axis]
            lo[axis], hi[axis] = sorted((wall_pos, wall_pos - sign * depth))
            boxes.append((lo, hi))
    cx, cy = rng.choice([-1.0, 1.0], 2)
    s = rng.uniform(0.35, 0.5)
    corner = np.array([cx * (HALF[0] - 0.05), cy * (HALF[1] - 0.05)])
    boxes.append((np.r_[np.minimum(corner, corner - [cx * s, cy * s]), 0.0],
                  np.r_[np.maximum(corner, corner - [cx * s, cy * s]), rng.uniform(0.4, 0.9)]))
    top = rng.uniform(0.7, 0.8)
    boxes.append((np.r_[-CENTRE_HALF, top - 0.04], np.r_[CENTRE_HALF, top]))  # table top
    for sx in (-1, 1):
        for sy in (-1, 1):
            leg = np.array([sx, sy]) * (CENTRE_HALF - 0.05)
            boxes.append((np.r_[leg - 0.025, 0.0], np.r_[leg + 0.025, top - 0.04]))
    return boxes


def build_room(seed: int) -> Room:
    """The room shell (inside faces) plus objects, each face with its own texture."""
    rng = np.random.default_rng(seed)
    boxes = _objects(rng)
    shell = [(np.r_[-HALF, 0.0], np.r_[HALF, HEIGHT], True, False)]
    faces = []
    for lo, hi, inward, skip in shell + [(lo, hi, False, lo[2] == 0.0) for lo, hi in boxes]:
        for origin, u, v, size, normal in _box_faces(lo, hi, inward, skip):
            shade = 0.55 + 0.45 * (0.5 + 0.5 * float(normal @ LIGHT))
            h = int(np.ceil(size[1] / TEXEL_M)) + 2
            w = int(np.ceil(size[0] / TEXEL_M)) + 2
            faces.append(Face(origin, u, v, size, normal, make_texture(rng, h, w, shade)))
    return Room(faces, boxes)
