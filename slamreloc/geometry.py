"""Rigid transforms and rotation helpers: the one place where pose conventions live.

A `Rigid3` maps points from frame *a* to frame *b*; its variable name says which:
`world_from_cam` maps camera coordinates to world coordinates (the camera-to-world pose of
7-Scenes `pose.txt` and TUM files), `cam_from_world` is its inverse (what PnP returns).
Units are metres; quaternions are Hamilton, scalar-last (x, y, z, w) as in TUM files.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from slamreloc.errors import InputError, escaped
from slamreloc.io.outputs import atomic_file, outputs_together
from slamreloc.io.numbers import number_problem, written_as_number

RIGID_TOL = 1e-3  # max |R^T R - I| and |det R - 1| accepted for a pose read from a file
MAX_COORDINATE = 1e9  # metres: beyond any map, and squares stay far from overflow


@dataclass(frozen=True)
class Rigid3:
    """x_b = rotation @ x_a + translation, for a transform named `b_from_a`."""

    rotation: np.ndarray  # (3, 3) float64
    translation: np.ndarray  # (3,) float64, metres

    @staticmethod
    def identity() -> Rigid3:
        return Rigid3(np.eye(3), np.zeros(3))

    @staticmethod
    def from_matrix(matrix: np.ndarray, tol: float = RIGID_TOL, source: str = "pose") -> Rigid3:
        """From a 4x4 (or 3x4) matrix; raises InputError if it is not a rigid transform."""
        m = np.asarray(matrix, dtype=np.float64)
        if m.shape not in ((4, 4), (3, 4)):
            raise InputError(f"{source}: expected a 4x4 matrix, got shape {m.shape}")
        if not np.all(np.isfinite(m)):
            raise InputError(f"{source}: matrix has non-finite values")
        if np.abs(m[:3, 3]).max() > MAX_COORDINATE:
            raise InputError(f"{source}: translation beyond {MAX_COORDINATE:g} m")
        if m.shape == (4, 4) and not np.allclose(m[3], [0, 0, 0, 1], atol=tol):
            raise InputError(f"{source}: last row is {m[3].tolist()}, not [0 0 0 1]")
        rot = m[:3, :3]
        if np.abs(rot).max() > 1 + tol or np.abs(rot.T @ rot - np.eye(3)).max() > tol \
                or abs(np.linalg.det(rot) - 1) > tol:  # a rotation's entries lie in [-1, 1]
            raise InputError(f"{source}: rotation block is not orthonormal (not a rigid pose)")
        return Rigid3(project_to_so3(rot), m[:3, 3].copy())

    @staticmethod
    def from_qt(quat_xyzw: np.ndarray, translation: np.ndarray, source: str = "pose") -> Rigid3:
        """From a unit quaternion (x, y, z, w; norm 1 within QUATERNION_NORM_TOL, the rule of
        every pose read: `unit_quaternion`, InputError naming `source` otherwise) and a
        translation (metres)."""
        return Rigid3(quat_to_matrix(unit_quaternion(quat_xyzw, source)),
                      np.asarray(translation, dtype=np.float64))

    def matrix(self) -> np.ndarray:
        """4x4 homogeneous matrix."""
        m = np.eye(4)
        m[:3, :3] = self.rotation
        m[:3, 3] = self.translation
        return m

    def matrix3x4(self) -> np.ndarray:
        return self.matrix()[:3]

    def inverse(self) -> Rigid3:
        rt = self.rotation.T
        return Rigid3(rt, -rt @ self.translation)

    def __matmul__(self, other: Rigid3) -> Rigid3:
        """Composition: (c_from_b @ b_from_a) is c_from_a."""
        return Rigid3(self.rotation @ other.rotation,
                      self.rotation @ other.translation + self.translation)

    def transform(self, points: np.ndarray) -> np.ndarray:
        """Apply to (N, 3) points."""
        return np.asarray(points) @ self.rotation.T + self.translation

    def quat_xyzw(self) -> np.ndarray:
        return matrix_to_quat(self.rotation)

    @property
    def center(self) -> np.ndarray:
        """Origin of frame a expressed in frame b (for world_from_cam: the camera centre)."""
        return self.translation


@dataclass(frozen=True)
class Sim3:
    """x_b = scale * rotation @ x_a + translation, for a similarity named `b_from_a` (two
    world frames of one scene that differ in scale, e.g. SfM units and metres)."""

    scale: float
    rotation: np.ndarray  # (3, 3)
    translation: np.ndarray  # (3,), metres of frame b

    def transform(self, points: np.ndarray) -> np.ndarray:
        """Apply to (N, 3) points."""
        return self.scale * np.asarray(points) @ self.rotation.T + self.translation

    def apply_to_pose(self, a_from_cam: Rigid3) -> Rigid3:
        """b_from_cam of a camera whose pose is given in frame a (the camera keeps its
        metric size: only its centre is scaled)."""
        return Rigid3(self.rotation @ a_from_cam.rotation,
                      self.transform(a_from_cam.translation[None])[0])

    @property
    def rigid(self) -> Rigid3:
        return Rigid3(self.rotation, self.translation)


def umeyama(source: np.ndarray, target: np.ndarray, with_scale: bool = True) -> Sim3:
    """target_from_source minimising sum |target - (s R source + t)|^2 over (N, 3) point pairs
    (Umeyama 1991; s = 1 unless `with_scale`)."""
    source, target = np.asarray(source, np.float64), np.asarray(target, np.float64)
    mu_s, mu_t = source.mean(0), target.mean(0)
    cov = (target - mu_t).T @ (source - mu_s) / len(source)
    u, d, vt = np.linalg.svd(cov)
    s = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        s[2, 2] = -1
    rot = u @ s @ vt
    var_s = np.mean(np.sum((source - mu_s) ** 2, axis=1))
    scale = float(np.trace(np.diag(d) @ s) / var_s) if with_scale and var_s > 0 else 1.0
    return Sim3(scale, rot, mu_t - scale * rot @ mu_s)


def align_poses(source: list[Rigid3], target: list[Rigid3], with_scale: bool = True) -> Sim3:
    """target_from_source between two sets of poses of the same cameras (world_from_cam in
    frames a and b): the rotation is the chordal mean of the cameras' rotation offsets
    R_b R_a^T, the scale (1 unless `with_scale`) and translation the least-squares fit of the
    camera centres under it. Unlike `umeyama` on centres alone, the rotation stays well
    determined for a nearly planar or straight trajectory."""
    rot = project_to_so3(sum(t.rotation @ s.rotation.T for s, t in zip(source, target)))
    a = np.array([p.translation for p in source])
    b = np.array([p.translation for p in target])
    mu_a, mu_b = a.mean(0), b.mean(0)
    spread = float(np.sum((a - mu_a) ** 2))
    # centres that coincide to within rounding (1e-12 of their size) leave the scale
    # undetermined: 1, not a ratio of rounding errors
    rounding = len(a) * (1e-12 * max(1.0, float(np.abs(a).max(initial=0.0)))) ** 2
    scale = (float(np.sum((b - mu_b) * ((a - mu_a) @ rot.T)) / spread)
             if spread > rounding and with_scale else 1.0)
    return Sim3(scale, rot, mu_b - scale * rot @ mu_a)


def project_to_so3(rot: np.ndarray) -> np.ndarray:
    """Nearest rotation matrix (SVD), to clean up rounding in poses read from text."""
    u, _, vt = np.linalg.svd(rot)
    r = u @ vt
    if np.linalg.det(r) < 0:
        u[:, -1] *= -1
        r = u @ vt
    return r


def quat_to_matrix(quat_xyzw: np.ndarray) -> np.ndarray:
    x, y, z, w = np.asarray(quat_xyzw, dtype=np.float64) / np.linalg.norm(quat_xyzw)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def matrix_to_quat(rot: np.ndarray) -> np.ndarray:
    """Rotation matrix to unit quaternion (x, y, z, w) with w >= 0."""
    m = np.asarray(rot, dtype=np.float64)
    tr = np.trace(m)
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, s / 4]
    else:
        i = int(np.argmax(np.diag(m)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * np.sqrt(1.0 + m[i, i] - m[j, j] - m[k, k])
        q = [0.0, 0.0, 0.0, (m[k, j] - m[j, k]) / s]
        q[i] = s / 4
        q[j] = (m[j, i] + m[i, j]) / s
        q[k] = (m[k, i] + m[i, k]) / s
    q = np.array(q)
    q /= np.linalg.norm(q)
    return -q if q[3] < 0 else q


def axis_angle_to_matrix(rotvec: np.ndarray) -> np.ndarray:
    """Rodrigues: rotation vector (radians) to matrix."""
    rotvec = np.asarray(rotvec, dtype=np.float64)
    angle = np.linalg.norm(rotvec)
    if angle < 1e-12:
        return np.eye(3)
    k = rotvec / angle
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * kx + (1 - np.cos(angle)) * kx @ kx


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray = (0, 0, 1)) -> Rigid3:
    """world_from_cam of a camera at `eye` looking at `target` (OpenCV: x right, y down, z fwd)."""
    eye, target, up = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return Rigid3(np.stack([x, y, z], axis=1), eye)


def rotation_angle_deg(rot: np.ndarray) -> float:
    cos = (np.trace(rot) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


def pose_error(world_from_cam_est: Rigid3, world_from_cam_gt: Rigid3) -> tuple[float, float]:
    """(translation error of the camera centre in metres, rotation error in degrees)."""
    dt = float(np.linalg.norm(world_from_cam_est.translation - world_from_cam_gt.translation))
    dr = rotation_angle_deg(world_from_cam_est.rotation.T @ world_from_cam_gt.rotation)
    return dt, dr


# two readings of one value agree within this, relative to the larger magnitude (at least 1):
# float noise of a text round trip, far below any difference a model or a pose means
AGREE_REL = 1e-9


def values_agree(a, b, rel: float = AGREE_REL) -> bool:
    """Whether two readings of the same numbers (same shape, any units) agree: every pair
    within `rel` of the larger magnitude (at least 1)."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    if a.shape != b.shape:
        return False
    scale = np.maximum(1.0, np.maximum(np.abs(a), np.abs(b)))
    return bool(np.all(np.abs(a - b) <= rel * scale))


def same_pose(a: Rigid3, b: Rigid3, rel: float = AGREE_REL) -> bool:
    """Whether two readings of a pose are one pose: rotation matrices and translations (metres
    or a model's units) agree within `rel` (`values_agree`); q and -q are the same rotation.
    The one rule for "the same pose, read twice" (a COLMAP model's .bin and .txt, a bag's or a
    TUM file's repeated stamp)."""
    return values_agree(a.rotation, b.rotation, rel) and \
        values_agree(a.translation, b.translation, rel)


def pose_gap(a: Rigid3, b: Rigid3) -> str:
    """"0.012 m and 0.5 deg apart": how far two poses are (`pose_error`: the camera centres'
    distance in metres, or the poses' units, and the rotation between them in degrees), for
    messages."""
    dt, dr = pose_error(a, b)
    return f"{dt:.3g} m and {dr:.3g} deg apart"


def tum_line(name: str, world_from_cam: Rigid3) -> str:
    """`name tx ty tz qx qy qz qw`, camera-to-world."""
    vals = [*world_from_cam.translation, *world_from_cam.quat_xyzw()]
    return name + " " + " ".join(f"{v:.6f}" for v in vals)


MAX_STAMP_S = 1e12  # seconds (31 700 years): larger values are ms, us or ns since an epoch


def check_stamp(stamp: float, source: str) -> float:
    """A timestamp (or frame index) in seconds: finite and within +-MAX_STAMP_S, else
    InputError naming `source`. The one rule of trajectory and odometry files, the command
    line and the service's frames."""
    if not np.isfinite(stamp):
        raise InputError(f"{source}: timestamp {stamp!r} is not finite")
    if abs(stamp) > MAX_STAMP_S:
        unit = next((u for u, scale in (("milliseconds", 1e3), ("microseconds", 1e6),
                                        ("nanoseconds", 1e9))
                     if abs(stamp) / scale <= 1e11), "another unit")  # Unix seconds < 1e11
        raise InputError(f"{source}: timestamp {stamp:.17g} is beyond {MAX_STAMP_S:g} s: "
                         f"timestamps are seconds (this looks like {unit})")
    return stamp


def parse_stamp(text: str, source: str) -> float:
    """A timestamp (or frame index) field: a number, in seconds (`check_stamp`), else
    InputError naming `source`."""
    problem = number_problem(text)  # one rule for numbers in text (slamreloc.io.numbers)
    if problem:
        raise InputError(f"{source}: timestamp {text[:40]!r} is {problem}")
    return check_stamp(float(text), source)


def parse_tum_line(line: str, source: str = "trajectory",
                   numeric_stamp: bool = False) -> tuple[str, Rigid3]:
    """`name tx ty tz qx qy qz qw` (camera-to-world) -> (name, world_from_cam).

    `numeric_stamp`: the first field must be a finite number (a timestamp or frame index).
    The quaternion must be a unit quaternion (`unit_quaternion`)."""
    parts = line.split()
    if len(parts) != 8:
        first = "timestamp" if numeric_stamp else "name"
        raise InputError(f"{source}: expected 8 fields '{first} tx ty tz qx qy qz qw', "
                         f"got {len(parts)}")
    if numeric_stamp:
        parse_stamp(parts[0], source)
    for text in parts[1:]:  # one rule for numbers in text (slamreloc.io.numbers)
        problem = number_problem(text)
        if problem:
            raise InputError(f"{source}: non-numeric pose value {text[:40]!r} ({problem}; "
                             "numbers are plain ASCII decimals such as -1.5 or 2e-3)")
    vals = np.array([float(text) for text in parts[1:]])
    if not np.all(np.isfinite(vals[:3])):
        raise InputError(f"{source}: invalid pose values in line {line.strip()[:120]!r}")
    if np.abs(vals[:3]).max() > MAX_COORDINATE:
        raise InputError(f"{source}: translation beyond {MAX_COORDINATE:g} m")
    return parts[0], Rigid3.from_qt(unit_quaternion(vals[3:], source), vals[:3])


QUATERNION_NORM_TOL = 1e-3  # |norm - 1|: files written with 4 decimals (TUM's) are within 2e-4


def unit_quaternion(quat, source: str) -> np.ndarray:
    """The quaternion (any component order) divided by its norm, if it is a unit quaternion:
    finite, norm 1 within QUATERNION_NORM_TOL; InputError naming `source` otherwise (a zero,
    far-from-unit or damaged quaternion: normalising it would make up a rotation). The one
    rule for every pose read: pose and trajectory files, COLMAP models, ROS bags, the
    service's messages."""
    q = np.asarray(quat, np.float64).reshape(-1)
    if q.shape != (4,) or not np.all(np.isfinite(q)):
        raise InputError(f"{source}: quaternion {_short_values(q)} is not 4 finite numbers")
    with np.errstate(over="ignore"):
        norm = float(np.sqrt(np.sum(q * q)))
    if not abs(norm - 1.0) <= QUATERNION_NORM_TOL:
        raise InputError(f"{source}: quaternion norm {norm:.6g}, not 1 (a unit quaternion is "
                         f"expected, within {QUATERNION_NORM_TOL:g})")
    return q / norm


def _short_values(v: np.ndarray) -> str:
    text = " ".join(f"{x:.6g}" for x in v[:8].tolist())
    return f"({text}{' ...' if len(v) > 8 else ''})"


def read_tum_trajectory(path, numeric_stamps: bool = False) -> list[tuple[str, Rigid3]]:
    """A TUM trajectory file: one `name tx ty tz qx qy qz qw` per line (camera-to-world);
    blank lines and `#` comments are skipped; lines and fields by TUM's line rule
    (`plain_lines`, the rule of rgb.txt). Errors name the file and line. A timestamp
    (a numeric first column) on more than one line is one pose read twice when the lines
    carry the same pose (`same_pose`), and is read once; with different poses it is an
    InputError naming both lines (`unique_stamps`): which one is the camera's is not for the
    reader to guess."""
    path = Path(path)
    return unique_stamps([(i, *parse_tum_line(line, f"{path}:{i}", numeric_stamps))
                          for i, line in _content_lines(path, "trajectory", plain=True)],
                         path)


def _stamp_value(text: str) -> float | None:
    """The timestamp (seconds) a first column holds, as `parse_stamp` reads it; None for a
    frame name (anything `parse_stamp` refuses)."""
    if number_problem(text):
        return None
    stamp = float(text)
    return stamp if np.isfinite(stamp) and abs(stamp) <= MAX_STAMP_S else None


STAMP_TOLERANCE_S = 1e-6  # stamps closer than this are one instant (far below any frame time)


class Instants:
    """What was read at each instant so far: stamps (seconds) within STAMP_TOLERANCE_S of each
    other are one instant, the one rule of every reader of stamped data (TUM files and lists,
    bag topics) for "given twice"."""

    def __init__(self) -> None:
        self._cells: dict[int, list[tuple[float, Any]]] = {}

    def setdefault(self, stamp: float, value: Any) -> tuple[float, Any]:
        """(stamp, value) first read at the instant of `stamp`; where none was, `stamp` and
        `value`, now kept."""
        row = self.get(stamp)
        if row[0] is not None:
            return row
        self._cells.setdefault(math.floor(stamp / STAMP_TOLERANCE_S), []).append((stamp, value))
        return stamp, value

    def get(self, stamp: float) -> tuple[float | None, Any]:
        """(stamp, value) read at the instant of `stamp`, or (None, None)."""
        cell = math.floor(stamp / STAMP_TOLERANCE_S)
        for c in (cell - 1, cell, cell + 1):
            for row in self._cells.get(c, ()):
                if abs(row[0] - stamp) <= STAMP_TOLERANCE_S:
                    return row
        return None, None


def same_instant_words(first: float, again: float) -> str:
    """How a stamp read again stands to the first of its instant, for a refusal."""
    return "repeats" if first == again else "is within 1 microsecond of"


def unique_stamps(rows: list[tuple[int, str, Rigid3]], path) -> list[tuple[str, Rigid3]]:
    """(first column, pose) of each (line number, first column, pose) row of the TUM file
    `path`, each instant once (`Instants`): a later row of an instant already read is dropped
    where its pose is the same (`same_pose`: float noise, q or -q) and an InputError
    `FILE:N: timestamp T repeats line M with a different pose (X m and Y deg apart)`
    otherwise. Frame names (non-numeric first columns) are left to the caller."""
    instants = Instants()
    out: list[tuple[str, Rigid3]] = []
    for line_no, first, pose in rows:
        stamp = _stamp_value(first)
        if stamp is not None:
            seen_stamp, (seen_line, seen_pose) = instants.setdefault(stamp, (line_no, pose))
            if seen_line != line_no:
                if same_pose(seen_pose, pose):
                    continue
                raise InputError(f"{path}:{line_no}: timestamp {first[:40]} "
                                 f"{same_instant_words(seen_stamp, stamp)} line {seen_line} "
                                 f"with a different pose ({pose_gap(seen_pose, pose)})")
        out.append((first, pose))
    return out


def refuse_json_text(text: str, path, what: str) -> None:
    """InputError `FILE: not a WHAT file (it is JSON, such as a report)` for text that starts
    as JSON does: a report or a map's metadata given where lines of poses belong would
    otherwise fail on some line with a message about its fields."""
    head = text.lstrip()[:1]
    if head in ("{", "["):
        raise InputError(f"{path}: not a {what} file (it is JSON, such as a report; a {what} "
                         "file holds one pose per line)")


def _content_lines(path: Path, what: str, plain: bool = False) -> list[tuple[int, str]]:
    """(line number, line) of a UTF-8 text file, blank lines and `#` comments skipped;
    an unreadable or binary file is an InputError naming it. `plain`: by the line rule of
    TUM's files (`slamreloc.io.fileio.plain_lines`: lines end at "\\n", fields are separated
    by spaces or tabs only, any other control character or blank refused)."""
    from slamreloc.io.fileio import plain_lines, read_text

    text = read_text(path, what, "max_text_bytes")
    refuse_json_text(text, path, what)
    lines = plain_lines(text, path, what) if plain else enumerate(text.splitlines(), 1)
    return [(i, line) for i, line in lines
            if line.strip() and not line.lstrip().startswith("#")]


NAMES_SUFFIX = ".names.txt"  # `evaluate --trajectory P.txt` names P's stamps in P.names.txt


def names_sidecar(path) -> Path:
    """The sidecar `<stem>.names.txt` (`stamp name` per line) beside a TUM file."""
    return Path(path).with_suffix(NAMES_SUFFIX)


def write_tum_trajectory(path, stamps, world_from_cam: list[Rigid3], comments=(),
                         names: list[str] | None = None) -> None:
    """A TUM file (`stamp tx ty tz qx qy qz qw`, camera-to-world, metres; `# comment` lines
    first) written atomically, and with `names` the `names_sidecar` (`stamp name` per line) that
    ties each stamp to its frame: both new, or (a failure, a full disk) both as they were."""
    rows = [f"{float(t):.6f}" for t in stamps]
    with outputs_together():  # both new, or both as they were
        with atomic_file(Path(path)) as tmp:
            tmp.write_text("".join(f"# {escaped(str(c))}\n" for c in comments)  # one line each
                           + "".join(tum_line(t, p) + "\n" for t, p in zip(rows, world_from_cam)))
        if names is not None:
            with atomic_file(names_sidecar(path)) as tmp:
                tmp.write_text("".join(f"{t} {n}\n" for t, n in zip(rows, names)))


def distinct_stamps(stamps) -> list[float]:
    """A trajectory's first column: the frames' timestamps (seconds), or their indices where
    timestamps repeat (several sequences), so that every row, and its frame name in the
    names sidecar, stays distinct."""
    stamps = [float(t) for t in stamps]
    return stamps if len(set(stamps)) == len(stamps) else [float(i) for i in range(len(stamps))]


def nearest_stamps(stamps, queries, max_dt: float) -> np.ndarray:
    """Index into `stamps` of the nearest stamp to each query (seconds); -1 beyond max_dt."""
    stamps, queries = np.asarray(stamps, float), np.asarray(queries, float)
    if len(stamps) == 0:
        return np.full(len(queries), -1)
    order = np.argsort(stamps, kind="stable")
    s = stamps[order]
    pos = np.clip(np.searchsorted(s, queries), 1, max(len(s) - 1, 1))
    left = np.clip(pos - 1, 0, len(s) - 1)
    pos = np.clip(pos, 0, len(s) - 1)
    pick = np.where(np.abs(s[left] - queries) <= np.abs(s[pos] - queries), left, pos)
    return np.where(np.abs(s[pick] - queries) <= max_dt, order[pick], -1)


@dataclass
class TumTrajectory:
    """A TUM file with its frame names. `stamps` is the first column, or the row's index
    where that column holds a frame name; `names` is None where no name is known."""

    stamps: np.ndarray  # (N,) float64
    names: list[str | None]
    poses: list[Rigid3]  # world_from_cam
    numeric: bool = False  # every first column is a number (names, if any, from the sidecar)


def read_names_sidecar(path) -> list[tuple[float, str]]:
    """`stamp name` lines -> (stamp seconds, name) per instant, in the file's order. Lines and
    fields by TUM's line rule (`plain_lines`, as the trajectory beside it); stamps within
    STAMP_TOLERANCE_S are one instant (`Instants`): one named twice alike is read once, with
    two names an InputError naming both lines. InputError on a bad line."""
    path = Path(path)
    instants = Instants()
    out: list[tuple[float, str]] = []
    for i, line in _content_lines(path, "frame names file", plain=True):
        parts = line.split(maxsplit=1)
        if len(parts) != 2:
            raise InputError(f"{path}:{i}: expected 'stamp name', got {line.strip()[:80]!r}")
        stamp, name = parse_stamp(parts[0], f"{path}:{i}"), parts[1].strip()
        first, (line_no, first_name) = instants.setdefault(stamp, (i, name))
        if line_no != i:
            if first_name == name:
                continue
            raise InputError(f"{path}:{i}: stamp {parts[0][:40]} "
                             f"{same_instant_words(first, stamp)} line {line_no} with another "
                             f"name ({escaped(name)[:80]}, not {escaped(first_name)[:80]})")
        out.append((stamp, name))
    return out


def read_named_trajectory(path) -> TumTrajectory:
    """A TUM file whose first column is a timestamp (or index) or a frame name, row by row.
    When every row is numeric, names come from the `names_sidecar` if there is one (what
    `evaluate --trajectory` writes). Errors name the file and line."""
    rows = read_tum_trajectory(path)
    stamps, names = [], []
    for i, (first, _) in enumerate(rows):
        if not written_as_number(first):
            stamps.append(float(i))  # a frame name (a named pose file, older `evaluate` files)
            names.append(first)
        else:  # a number, or written as one (1e400, nan): a timestamp, checked as one
            stamps.append(parse_stamp(first, str(path)))
            names.append(None)
    sidecar = names_sidecar(path)
    numeric = bool(rows) and all(n is None for n in names)
    if numeric and os.path.lexists(sidecar):  # given: it names every pose, and only those
        listed = read_names_sidecar(sidecar)  # one row per instant (a FIFO: refused)
        table = Instants()
        for stamp, name in listed:
            table.setdefault(stamp, name)
        names, matched = [], set()
        for stamp in stamps:
            first, name = table.get(stamp)
            if first is None:
                raise InputError(f"{sidecar}: names no frame for the stamp {stamp:.6f} of {path} "
                                 "(a trajectory's names file has one line per pose)")
            names.append(name)
            matched.add(first)
        extra = len(listed) - len(matched)
        if extra:
            raise InputError(f"{sidecar}: names {extra} stamp(s) that {path} has no pose for "
                             "(a trajectory's names file has one line per pose)")
    return TumTrajectory(np.array(stamps, dtype=np.float64), names, [p for _, p in rows],
                         numeric)


def project(points_cam: np.ndarray, fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """Pinhole projection of (N, 3) camera-frame points to (N, 2) pixels (OpenCV convention)."""
    z = points_cam[:, 2:3]
    return points_cam[:, :2] / z * np.array([fx, fy]) + np.array([cx, cy])


def reprojection_px(cam_from_world: Rigid3, points2d: np.ndarray, points3d: np.ndarray,
                    intrinsics: tuple[float, float, float, float],
                    min_depth_m: float = 1e-6) -> np.ndarray:
    """(N,) pixel distance between each keypoint (undistorted pixels) and its world point
    (metres) projected by the pose with pinhole `intrinsics` (fx, fy, cx, cy: a camera's
    `params()`); inf for a NaN point or one at most `min_depth_m` in front of the camera."""
    x = cam_from_world.transform(np.asarray(points3d, np.float64))
    with np.errstate(invalid="ignore", divide="ignore"):
        err = np.linalg.norm(project(x, *intrinsics) - points2d, axis=1)
    return np.where(x[:, 2] > min_depth_m, err, np.inf)
