"""Colours of the layers and the error colour scale (with its HTML legend)."""

from __future__ import annotations

import numpy as np

GROUND_TRUTH = (40, 170, 60)  # green, as in the paper's figure
ESTIMATE = (220, 40, 40)  # red
TRAINING_CAMERA = (70, 110, 200)
CURRENT_FRAME = (250, 200, 0)
SELECTED = (255, 120, 0)
FAILURE = (200, 0, 200)  # magenta: where a failed query really was
PSEUDO_POINTS = (255, 0, 220)
PSEUDO_FRAMES = (255, 150, 0)
ERROR_LINK = (150, 150, 150)

EVENT_COLORS = {  # (accepted, rejected)
    "relocalization": ((0, 160, 255), (255, 140, 0)),
    "loop_closure": ((0, 200, 200), (255, 60, 60)),
    "recovery": ((30, 200, 30), (120, 120, 120)),
    "kidnap": ((160, 0, 220), (160, 0, 220)),
    "tracking_lost": ((90, 90, 90), (90, 90, 90)),
    "other": ((200, 200, 0), (120, 120, 0)),
}
EDGE_COLORS = {  # accepted colour per edge type; rejected edges are drawn in REJECTED_EDGE
    "odometry": (140, 140, 140),
    "loop_closure": (0, 200, 200),
    "relocalization": (0, 160, 255),
    "prior": (30, 200, 30),
}
REJECTED_EDGE = (255, 60, 60)
OTHER_EDGE = (200, 200, 0)

# Error scale: green (0) -> yellow -> red (at ERROR_MAX_M and beyond).
ERROR_STOPS = np.array([[40, 170, 60], [250, 210, 0], [230, 30, 30]], dtype=np.float64)
ERROR_MAX_M = 0.20
# Height scale (no images): a viridis-like ramp.
HEIGHT_STOPS = np.array([[68, 1, 84], [59, 82, 139], [33, 145, 140], [94, 201, 98],
                         [253, 231, 37]], dtype=np.float64)


def ramp(values: np.ndarray, stops: np.ndarray) -> np.ndarray:
    """Map values in [0, 1] (clipped; NaN -> 0) through colour stops to (N, 3) uint8."""
    v = np.nan_to_num(np.clip(np.asarray(values, dtype=np.float64), 0, 1)) * (len(stops) - 1)
    i = np.minimum(v.astype(int), len(stops) - 2)
    f = (v - i)[:, None]
    return np.round(stops[i] * (1 - f) + stops[i + 1] * f).astype(np.uint8)


def error_colors(errors_m: np.ndarray, max_m: float = ERROR_MAX_M) -> np.ndarray:
    """Errors in metres -> colours; NaN (unknown) -> grey."""
    errors_m = np.asarray(errors_m, dtype=np.float64)
    out = ramp(errors_m / max_m, ERROR_STOPS)
    out[~np.isfinite(errors_m)] = ERROR_LINK
    return out


def height_colors(points: np.ndarray, up: np.ndarray) -> np.ndarray:
    h = np.asarray(points, dtype=np.float64) @ np.asarray(up, dtype=np.float64)
    if len(h) == 0:
        return np.zeros((0, 3), np.uint8)
    lo, hi = np.percentile(h, [2, 98])
    return ramp((h - lo) / max(hi - lo, 1e-9), HEIGHT_STOPS)


def css(rgb) -> str:
    return "rgb({},{},{})".format(*(int(c) for c in rgb))


def error_legend_html(max_m: float = ERROR_MAX_M) -> str:
    stops = ", ".join(css(c) for c in ERROR_STOPS)
    return (f'<div style="font-size:0.8em;padding:0 0.5em">'
            f'<div>position error</div>'
            f'<div style="height:10px;border-radius:3px;background:linear-gradient(to right, '
            f'{stops})"></div><div style="display:flex;justify-content:space-between">'
            f'<span>0 cm</span><span>{100 * max_m / 2:.0f} cm</span>'
            f'<span>&ge; {100 * max_m:.0f} cm</span></div></div>')


def swatches_html(items: list[tuple[str, tuple[int, int, int]]]) -> str:
    rows = "".join(f'<div><span style="display:inline-block;width:0.8em;height:0.8em;'
                   f'margin-right:0.4em;background:{css(c)}"></span>{name}</div>'
                   for name, c in items)
    return f'<div style="font-size:0.8em;padding:0 0.5em">{rows}</div>'
