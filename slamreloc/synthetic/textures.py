"""Procedural face textures: colour value noise plus random shapes, rich in SIFT features.

Texture images are (H, W, 3) uint8 RGB, one texel = `texel_m` metres on the face (default 5 mm).
Every call draws from the caller's `numpy.random.Generator`, so textures are seed-deterministic
and no two faces share one.
"""

from __future__ import annotations

import cv2
import numpy as np

_GLYPHS = "ABCDEFGHKMNPRSTUVWXYZ0123456789#%&@"
_FONTS = (cv2.FONT_HERSHEY_SIMPLEX, cv2.FONT_HERSHEY_DUPLEX, cv2.FONT_HERSHEY_COMPLEX,
          cv2.FONT_HERSHEY_TRIPLEX, cv2.FONT_HERSHEY_PLAIN)


def value_noise(rng: np.random.Generator, height: int, width: int, octaves: int = 5,
                cell: float | None = None) -> np.ndarray:
    """Smooth multi-octave colour noise in [-1, 1] roughly, (H, W, 3) float32; `cell` = texels
    between lattice points of the coarsest octave (default a third of the image)."""
    out = np.zeros((height, width, 3), np.float32)
    cell, amp = cell or max(height, width) / 3.0, 1.0
    for _ in range(octaves):
        gh, gw = max(2, int(height / cell) + 2), max(2, int(width / cell) + 2)
        grid = rng.uniform(-1, 1, (gh, gw, 3)).astype(np.float32)
        out += amp * cv2.resize(grid, (width, height), interpolation=cv2.INTER_CUBIC)
        cell, amp = cell / 2.5, amp * 0.6
    return out


def _colour(rng: np.random.Generator) -> tuple[int, int, int]:
    return tuple(int(c) for c in rng.integers(0, 256, 3))


def _draw_shape(img: np.ndarray, rng: np.random.Generator, size: float) -> None:
    """One random shape of about `size` texels, at a random place, in a random colour."""
    h, w = img.shape[:2]
    c = (int(rng.integers(0, w)), int(rng.integers(0, h)))
    col, kind = _colour(rng), int(rng.integers(0, 7))
    thick = int(rng.integers(1, max(2, int(size / 8) + 2)))
    r = max(1, int(size / 2))
    if kind == 0:
        cv2.circle(img, c, r, col, -1, cv2.LINE_AA)
    elif kind == 1:
        cv2.circle(img, c, r, col, thick, cv2.LINE_AA)
    elif kind in (2, 3):
        d = (int(rng.uniform(0.3, 1.0) * size), int(rng.uniform(0.3, 1.0) * size))
        cv2.rectangle(img, c, (c[0] + d[0], c[1] + d[1]), col, -1 if kind == 2 else thick)
    elif kind == 4:
        n = int(rng.integers(3, 7))
        ang = np.sort(rng.uniform(0, 2 * np.pi, n))
        rad = rng.uniform(0.4, 1.0, n) * r
        pts = np.stack([c[0] + rad * np.cos(ang), c[1] + rad * np.sin(ang)], 1).astype(np.int32)
        cv2.fillPoly(img, [pts], col, cv2.LINE_AA)
    elif kind == 5:
        a = rng.uniform(0, 2 * np.pi)
        end = (int(c[0] + size * np.cos(a)), int(c[1] + size * np.sin(a)))
        cv2.line(img, c, end, col, thick, cv2.LINE_AA)
    else:
        text = "".join(rng.choice(list(_GLYPHS), int(rng.integers(1, 5))))
        font = _FONTS[int(rng.integers(0, len(_FONTS)))]
        cv2.putText(img, text, c, font, size / 30.0, col, max(1, thick // 2), cv2.LINE_AA)


def make_texture(rng: np.random.Generator, height: int, width: int,
                 shade: float = 1.0) -> np.ndarray:
    """(H, W, 3) uint8 texture: noise base + multi-scale shapes, brightness scaled by `shade`."""
    base = rng.uniform(60, 200, 3).astype(np.float32)
    img = base + rng.uniform(25, 60) * value_noise(rng, height, width)
    img = np.clip(img, 0, 255).astype(np.uint8)
    area = height * width
    # few small shapes: many identical dots would give SIFT descriptors that look alike all
    # over the room; the fractal grain below makes every patch unique instead
    for count, lo, hi in ((area / 5000, 40, 180), (area / 1500, 12, 40), (area / 2500, 4, 12)):
        hi = max(lo, min(hi, max(height, width)))
        sizes = np.exp(rng.uniform(np.log(lo), np.log(hi), int(count) + 2))
        for size in sizes:  # scale by scale, large first, so small details stay on top
            _draw_shape(img, rng, float(size))
    grain = value_noise(rng, height, width, octaves=4, cell=60.0)  # fractal detail everywhere
    img = img.astype(np.float32) * (1.0 + 0.3 * grain)
    img = cv2.GaussianBlur(img * shade, (0, 0), 0.6)
    return np.clip(img + 0.5, 0, 255).astype(np.uint8)
