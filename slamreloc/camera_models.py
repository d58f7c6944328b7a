"""Camera models: COLMAP's lens-distortion models, their maths, and COLMAP camera strings.

slamreloc works in the *pinhole* camera of a distorted camera: keypoints are undistorted once,
right after extraction (`Camera.undistort`), into a pinhole camera with the same fx, fy, cx,
cy; triangulation, PnP, depth back-projection and the map all see pinhole pixels. Images are
never resampled (depth maps are: `Camera.undistort_image` maps them onto the pinhole grid).
This module holds the maths on plain values; `slamreloc.types.Camera` wraps it.

Distortion parameters act on normalised image coordinates (x, y) = ((u - cx) / fx,
(v - cy) / fy) exactly as COLMAP (and OpenCV, whose formulas are the same) define them:

    SIMPLE_RADIAL   f cx cy k                 x' = x (1 + k r^2)
    RADIAL          f cx cy k1 k2             x' = x (1 + k1 r^2 + k2 r^4)
    OPENCV          fx fy cx cy k1 k2 p1 p2   radial k1 k2, tangential p1 p2
    FULL_OPENCV     fx fy cx cy k1 k2 p1 p2 k3 k4 k5 k6   rational radial
    OPENCV_FISHEYE  fx fy cx cy k1 k2 k3 k4   equidistant: theta_d = theta (1 + k1 theta^2 + ...)

Pixel convention: slamreloc's (OpenCV's) pixel centres are at integer coordinates; COLMAP's
at +0.5. Camera strings and COLMAP files are in COLMAP's convention and converted here.
"""

from __future__ import annotations

import re
from functools import lru_cache

import numpy as np

from slamreloc.errors import InputError
from slamreloc.io.numbers import DECIMAL_WORDS, number_problem

# COLMAP model name -> its parameter names; "f" means fx = fy
PARAMS: dict[str, tuple[str, ...]] = {
    "SIMPLE_PINHOLE": ("f", "cx", "cy"),
    "PINHOLE": ("fx", "fy", "cx", "cy"),
    "SIMPLE_RADIAL": ("f", "cx", "cy", "k"),
    "RADIAL": ("f", "cx", "cy", "k1", "k2"),
    "OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"),
    "FULL_OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"),
    "OPENCV_FISHEYE": ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4"),
}
MODELS = tuple(PARAMS)
DISTORTED_MODELS = ("SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV", "OPENCV_FISHEYE")
MAX_DISTORTION = 1e3  # |k|, |p| beyond this is no lens
COLMAP_CENTRE = 0.5  # COLMAP's principal point minus OpenCV's, pixels


def n_distortion(model: str) -> int:
    """Number of distortion parameters of a COLMAP model."""
    return sum(1 for p in PARAMS[model] if p[0] in "kp")


def distortion_problem(model: str, distortion) -> str | None:
    """What is wrong with a model name and its distortion parameters (None when nothing)."""
    if model not in PARAMS or model == "SIMPLE_PINHOLE":
        return (f"unknown camera model {str(model)[:40]!r} (known: PINHOLE, "
                f"{', '.join(DISTORTED_MODELS)})")
    if len(distortion) != n_distortion(model):
        return (f"{model} has {n_distortion(model)} distortion parameters, got "
                f"{len(distortion)}")
    for name, v in zip((p for p in PARAMS[model] if p[0] in "kp"), distortion):
        if isinstance(v, bool) or not isinstance(v, (int, float, np.number)) or \
                not abs(float(v)) <= MAX_DISTORTION:
            return f"distortion {name} must be a finite number within +-{MAX_DISTORTION:g}"
    return None


def fold_problem(model: str, distortion, width: int, height: int, fx: float, fy: float,
                 cx: float, cy: float) -> str | None:
    """Why a lens cannot be undone over its image (None when it can): towards the middle of
    each image edge, the distorted radius must keep growing with the ideal radius until it
    reaches that edge (normalised coordinates), so every pixel of the circle inscribed in the
    image has one direction. A lens that folds back before (a SIMPLE_RADIAL k of -10 on a
    60-degree view) maps two directions onto one pixel, or none, and undistortion would return
    a wrong one without a word. The corners beyond that circle are not asked for: calibrations
    of wide lenses often hold only inside it."""
    if model == "PINHOLE" or not len(distortion):
        return None
    return _fold_problem(model, tuple(float(v) for v in distortion), int(width), int(height),
                         float(fx), float(fy), float(cx), float(cy))


@lru_cache(maxsize=256)
def _fold_problem(model: str, distortion: tuple[float, ...], width: int, height: int,
                  fx: float, fy: float, cx: float, cy: float) -> str | None:
    edges = np.array([[0, cy], [width - 1, cy], [cx, 0], [cx, height - 1]], np.float64)
    ideal = np.geomspace(1e-4, 1e3, 6000)[:, None]  # ideal radii along a direction (0.3 %)
    for edge in edges:
        ray = (edge - [cx, cy]) / [fx, fy]
        reach = float(np.linalg.norm(ray))
        if reach == 0:
            continue
        unit = ray / reach
        with np.errstate(all="ignore"):
            out = distort_normalized(model, distortion, ideal * unit) @ unit
        beyond = np.flatnonzero(~(out < reach))  # reached (or no longer a number)
        upto = out[:beyond[0] + 1] if len(beyond) else out
        if (model == "OPENCV_FISHEYE" and not len(beyond) and np.all(np.diff(upto) > 0)
                and reach > distort_normalized(model, distortion, 1e6 * unit[None]) @ unit):
            return _beyond_fisheye(f"{edge[0]:g}, {edge[1]:g}", fx, fy)
        if (not len(beyond) or not np.isfinite(upto[-1])
                or not np.all(np.diff(upto) > 0)):
            return (f"its distortion {list(distortion)} folds back inside the image (towards "
                    f"pixel ({edge[0]:g}, {edge[1]:g}) the distorted radius stops growing "
                    "before the image's edge), so its pixels cannot be undistorted")
    return _fold_in_circle(model, distortion, width, height, fx, fy, cx, cy)


def _beyond_fisheye(pixel: str, fx: float, fy: float) -> str:
    """The problem of a fisheye camera whose image reaches past 90 degrees off its axis
    towards `pixel` ("x, y"): its focal lengths are too short for the image."""
    return (f"towards pixel ({pixel}) the image reaches beyond what the fisheye lens sees "
            "(more than 90 degrees off its axis: a field of view over 180 degrees at "
            f"fx={fx:g}, fy={fy:g}); check the focal lengths")


def _fold_in_circle(model: str, distortion: tuple[float, ...], width: int, height: int,
                    fx: float, fy: float, cx: float, cy: float) -> str | None:
    """The fold test in every direction, not only along the axes (tangential terms fold the
    mapping sideways), over the circle inscribed in the image (centred on the image, wherever
    the principal point lies): along 360 rays of ideal directions from the optical axis, up
    to where the distorted point leaves that circle after entering it, the mapping must keep
    its orientation (the Jacobian's determinant, by differences in radius and angle, stays
    positive), and a ray that enters the circle must leave it. Then each pixel inside the
    circle has exactly one direction. A fisheye ray that keeps its orientation and is still
    inside the circle at 90 degrees off the axis (the last radius, 89.94 degrees) is no fold:
    the circle reaches past what the lens sees, and that is said instead."""
    centre, radius_px = np.array([(width - 1) / 2, (height - 1) / 2]), min(width, height) / 2
    angles = np.linspace(0, 2 * np.pi, 360, endpoint=False)
    radii = np.geomspace(1e-3, 1e3, 1200)  # steps of 1.2 %
    step = 1e-5  # radians: the angular difference
    with np.errstate(all="ignore"):
        rays = [distort_normalized(model, distortion,
                                   (radii[:, None, None] * np.stack(
                                       [np.cos(angles + a), np.sin(angles + a)], 1)
                                    ).reshape(-1, 2)).reshape(len(radii), len(angles), 2)
                for a in (0.0, step)]
        offset = rays[0] * [fx, fy] + [cx, cy] - centre
        inside = np.hypot(offset[..., 0], offset[..., 1]) < radius_px  # NaN: outside
        outward = np.diff(rays[0], axis=0)
        sideways = (rays[1] - rays[0])[:-1]
        det = outward[..., 0] * sideways[..., 1] - outward[..., 1] * sideways[..., 0]
    steps = np.arange(len(radii))[:, None]
    # each ray's own branch ends where its orientation first flips (a barrel lens's distorted
    # radius peaks, then turns back through the principal point: a branch of directions
    # beyond the lens's field that undistortion never takes, which may cross the circle
    # when the principal point lies outside it, as in a crop)
    flip = ~(det > 0)
    flips = flip.any(axis=0)
    branch_end = np.where(flips, flip.argmax(axis=0), len(radii) - 1)  # its last step
    own = steps <= branch_end[None, :]
    entered = (inside & own).any(axis=0)
    first_in = np.where(entered, (inside & own).argmax(axis=0), len(radii))
    out_after = ~inside & own & (steps > first_in[None, :])  # outside again, after entering
    left = out_after.any(axis=0)
    bad = entered & ~left & flips  # flips while inside: two directions meet there
    stuck = entered & ~left & ~flips  # still inside at the last radius: never leaves
    if not stuck.any() and not bad.any():
        return _circle_reached(model, distortion, width, height, fx, fy, cx, cy,
                               radii[branch_end])
    ray = int(np.argmax(bad)) if bad.any() else int(np.argmax(stuck))
    step_at = int(branch_end[ray])
    where = rays[0][step_at, ray] * [fx, fy] + [cx, cy]
    if model == "OPENCV_FISHEYE" and not bad.any():
        return _beyond_fisheye(f"{where[0]:.0f}, {where[1]:.0f}", fx, fy)
    return (f"its distortion {list(distortion)} folds back inside the image (near pixel "
            f"({where[0]:.0f}, {where[1]:.0f}) two directions meet on one pixel, or none "
            "reaches it), so its pixels cannot be undistorted")


def colmap_values(model: str, params, source: str) -> tuple[str, float, float, float, float,
                                                          tuple[float, ...]]:
    """(canonical model, fx, fy, cx, cy, distortion) of a COLMAP model and its parameter list;
    the principal point converted to OpenCV's convention. Range checks are the Camera's."""
    if model not in PARAMS:
        raise InputError(f"{source}: unknown camera model {model[:40]!r} (known: "
                         f"{', '.join(MODELS)})")
    names = PARAMS[model]
    if len(params) != len(names):
        raise InputError(f"{source}: {model} takes {len(names)} parameters "
                         f"({' '.join(names)}), got {len(params)}")
    values = dict(zip(names, (float(p) for p in params)))
    fx = fy = values.get("f", 0.0)
    fx, fy = values.get("fx", fx), values.get("fy", fy)
    distortion = tuple(values[p] for p in names if p[0] in "kp")
    return ("PINHOLE" if model == "SIMPLE_PINHOLE" else model, fx, fy,
            values["cx"] - COLMAP_CENTRE, values["cy"] - COLMAP_CENTRE, distortion)


def split_camera_string(text: str, source: str) -> tuple[str, int, int, list[float]]:
    """(model, width, height, parameters) of `"OPENCV 640 480 fx fy cx cy k1 k2 p1 p2"`, a
    line of COLMAP's cameras.txt with or without its camera id."""
    # the words as COLMAP's reader splits them: ASCII blanks (a no-break space is no separator)
    if "\n" in text.strip(" \t\r\n"):
        raise InputError(f"{source}: more than one line; a camera is one line 'MODEL WIDTH "
                         "HEIGHT PARAMS...'")
    words = [w for w in re.split(r"[ \t]+", text.strip(" \t\r\n")) if w]
    if words and words[0].isdigit() and len(words) > 1 and words[1] in PARAMS:
        words = words[1:]  # a cameras.txt line: CAMERA_ID MODEL WIDTH HEIGHT PARAMS
    if len(words) < 3 or words[0] not in PARAMS:  # COLMAP's names, upper case, as cameras.txt
        raise InputError(f"{source}: expected 'MODEL WIDTH HEIGHT PARAMS...' with MODEL one of "
                         f"{', '.join(MODELS)}, got {text[:60]!r}")
    # one rule for numbers in text (slamreloc.io.numbers); a size is plain digits, unsigned
    if not all(w.isascii() and w.isdigit() for w in words[1:3]):
        raise InputError(f"{source}: width and height must be whole numbers (plain decimal "
                         f"digits), got {text[:60]!r}")
    for word in words[3:]:
        problem = number_problem(word)
        if problem is not None:  # the rule's own reason: `1e999` is beyond a number's range
            raise InputError(f"{source}: parameter {word[:40]!r} is {problem} "
                             f"({DECIMAL_WORDS}), in {text[:60]!r}")
    return words[0], int(words[1]), int(words[2]), [float(w) for w in words[3:]]


def colmap_head(model: str, fx: float, fy: float, cx: float, cy: float) -> list[float]:
    """The focal and principal-point parameters of a COLMAP model, COLMAP's convention."""
    cx, cy = cx + COLMAP_CENTRE, cy + COLMAP_CENTRE
    return [0.5 * (fx + fy), cx, cy] if PARAMS[model][0] == "f" else [fx, fy, cx, cy]


def _circle_reached(model: str, distortion: tuple[float, ...], width: int, height: int,
                    fx: float, fy: float, cx: float, cy: float,
                    branch_radius: np.ndarray) -> str | None:
    """The last part of the fold test: every pixel of the circle inscribed in the image
    (sampled: 360 directions, 24 radii) undistorts to a direction that distorts back onto it
    (within 0.05 px) and lies on its ray's own branch (`branch_radius`: the ideal radius where
    each of `_fold_in_circle`'s 360 rays, at angles 2 pi k / 360, first flips, or its last).
    The branches keep their orientation; this finds a part of the circle that none of them
    reaches (a lens whose radius peaks before the circle's far side, seen from a principal
    point outside it), and pixels that undistortion takes past a branch's end (a strong
    pincushion, a rational lens's pole), whose direction is then another than the lens
    gives them."""
    centre, radius_px = np.array([(width - 1) / 2, (height - 1) / 2]), min(width, height) / 2
    angles = np.linspace(0, 2 * np.pi, 360, endpoint=False)
    radius = np.linspace(0, radius_px - 0.5, 24)[:, None]
    pixels = np.stack([centre[0] + radius * np.cos(angles), centre[1] + radius * np.sin(angles)],
                      -1).reshape(-1, 2)
    f, c = np.array([fx, fy]), np.array([cx, cy])
    with np.errstate(all="ignore"):
        ideal = undistort_normalized(model, distortion, (pixels - c) / f)
        back = distort_normalized(model, distortion, ideal) * f + c
        ray = np.arctan2(ideal[:, 1], ideal[:, 0]) / (2 * np.pi) * len(branch_radius)
        below = np.floor(ray).astype(np.int64) % len(branch_radius)  # the two rays around it
        reach = np.maximum(branch_radius[below], branch_radius[(below + 1) % len(branch_radius)])
        miss = ~(np.hypot(*(back - pixels).T) < 0.05) | ~(np.hypot(*ideal.T) <= reach * 1.03)
    if not miss.any():
        return None
    where = pixels[int(np.argmax(miss))]
    return (f"its distortion {list(distortion)} folds back inside the image (near pixel "
            f"({where[0]:.0f}, {where[1]:.0f}) two directions meet on one pixel, or none "
            "reaches it), so its pixels cannot be undistorted")


def distort_normalized(model: str, distortion, xy: np.ndarray) -> np.ndarray:
    """(N, 2) ideal normalised coordinates -> distorted normalised coordinates."""
    xy = np.asarray(xy, np.float64)
    x, y = xy[:, 0], xy[:, 1]
    d = tuple(float(v) for v in distortion)
    r2 = x * x + y * y
    if model == "PINHOLE":
        return xy.copy()
    if model == "OPENCV_FISHEYE":
        r = np.sqrt(r2)
        theta = np.arctan(r)
        t2 = theta * theta
        theta_d = theta * (1 + t2 * (d[0] + t2 * (d[1] + t2 * (d[2] + t2 * d[3]))))
        scale = np.where(r > 1e-12, theta_d / np.maximum(r, 1e-12), 1.0)
        return xy * scale[:, None]
    if model == "SIMPLE_RADIAL":
        k1, k2, p1, p2, k3, k4, k5, k6 = d[0], 0, 0, 0, 0, 0, 0, 0
    elif model == "RADIAL":
        k1, k2, p1, p2, k3, k4, k5, k6 = d[0], d[1], 0, 0, 0, 0, 0, 0
    elif model == "OPENCV":
        k1, k2, p1, p2, k3, k4, k5, k6 = (*d, 0, 0, 0, 0)
    elif model == "FULL_OPENCV":
        k1, k2, p1, p2, k3, k4, k5, k6 = d
    else:
        raise ValueError(f"unknown camera model {model}")
    radial = (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.stack([xd, yd], axis=1)


def undistort_normalized(model: str, distortion, xy_d: np.ndarray,
                         iterations: int = 40) -> np.ndarray:
    """Inverse of `distort_normalized` by Gauss-Newton with a numeric Jacobian (as COLMAP
    does), each step halved until it brings the point closer (so it never jumps across a
    pole of a rational lens to another root far away); converges to ~1e-12 for any lens
    whose distortion is monotonic over the image."""
    xy_d = np.asarray(xy_d, np.float64)
    if model == "PINHOLE" or not len(xy_d):
        return xy_d.copy()
    xy = xy_d.copy()
    eps = 1e-7
    f = distort_normalized(model, distortion, xy) - xy_d
    for _ in range(iterations):
        fx = (distort_normalized(model, distortion, xy + [eps, 0]) - xy_d - f) / eps
        fy = (distort_normalized(model, distortion, xy + [0, eps]) - xy_d - f) / eps
        a, b, c, d = fx[:, 0], fy[:, 0], fx[:, 1], fy[:, 1]
        det = a * d - b * c
        det = np.where(np.abs(det) < 1e-12, 1e-12, det)
        step = np.stack([(d * f[:, 0] - b * f[:, 1]) / det,
                         (-c * f[:, 0] + a * f[:, 1]) / det], axis=1)
        xy, f, step = _closer(model, distortion, xy_d, xy, f, step)
        if np.max(np.abs(step), initial=0) < 1e-12:
            break
    return xy


def _closer(model: str, distortion, xy_d: np.ndarray, xy: np.ndarray, f: np.ndarray,
            step: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(new points, their residuals, the steps taken) for Gauss-Newton steps `step` from `xy`
    (residuals `f`): a step that does not bring a point's distortion closer to `xy_d` is
    halved, up to 30 times (then the point stays)."""
    before = np.hypot(f[:, 0], f[:, 1])
    todo = np.arange(len(xy))
    new_xy, new_f, taken = xy.copy(), f.copy(), np.zeros_like(step)
    for _ in range(30):
        trial = xy[todo] - step[todo]
        with np.errstate(all="ignore"):
            res = distort_normalized(model, distortion, trial) - xy_d[todo]
        ok = np.hypot(res[:, 0], res[:, 1]) <= before[todo]  # NaN: not closer
        new_xy[todo[ok]], new_f[todo[ok]], taken[todo[ok]] = trial[ok], res[ok], step[todo[ok]]
        todo = todo[~ok]
        if not len(todo):
            break
        step[todo] *= 0.5
    return new_xy, new_f, taken


def map_pixels(uv: np.ndarray, fx: float, fy: float, cx: float, cy: float, model: str,
               distortion, undistort: bool) -> np.ndarray:
    """(N, 2) image pixels -> pinhole pixels (`undistort`), or back, through normalised
    coordinates; unchanged for a pinhole camera."""
    uv = np.asarray(uv)
    if model == "PINHOLE":
        return uv
    f, c = np.array([fx, fy]), np.array([cx, cy])
    fn = undistort_normalized if undistort else distort_normalized
    return (fn(model, distortion, (uv - c) / f) * f + c).astype(uv.dtype, copy=False)


def pinhole_grid_sources(width: int, height: int, fx: float, fy: float, cx: float, cy: float,
                         model: str, distortion) -> np.ndarray:
    """(height, width, 2) float32: for each pinhole pixel, where it lies in the distorted
    image (a `cv2.remap` map)."""
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    src = map_pixels(np.stack([u.ravel(), v.ravel()], axis=1), fx, fy, cx, cy, model,
                     distortion, undistort=False)
    return src.reshape(height, width, 2).astype(np.float32)
