"""TUM RGB-D layout: rgb.txt, depth.txt, groundtruth.txt (timestamps, camera-to-world poses).

Depth is registered to the RGB images (TUM ships it so), 5000 units per metre. Default RGB
intrinsics are the ROS defaults fx = fy = 525, cx = 319.5, cy = 239.5; `intrinsics.txt`
(3x3) at the root overrides them. Each RGB image takes the ground-truth pose and the depth
image nearest in time (within 20 ms); without a pose it is kept, unposed.
"""

from __future__ import annotations

from pathlib import Path, PurePosixPath

import numpy as np

from slamreloc.datasets.base import Dataset
from slamreloc.datasets.io import check_frame_files, image_size, read_intrinsics, read_text
from slamreloc.errors import InputError
from slamreloc.io.fileio import optional_file, plain_lines
from slamreloc.geometry import Instants, parse_stamp, read_tum_trajectory, same_instant_words
from slamreloc.types import Camera, Frame

MAX_DT = 0.02  # seconds


def is_tum(root: Path) -> bool:
    return (root / "rgb.txt").is_file()


def _read_list(path: Path, n_fields: int) -> list[list[str]]:
    """The `timestamp file` rows of rgb.txt / depth.txt. A timestamp on two lines naming the
    same file is one row read twice (read once); naming different files it is an InputError
    naming both lines: which image is that instant's is not for the reader to guess. The
    rows are in time order (a stamp earlier than the line before is an InputError: tracking
    would run the sequence backwards in places). Lines and fields by `plain_lines`' rule (the
    C++ client reads rgb.txt by it too): lines end at "\\n", fields are separated by spaces or
    tabs, any other control character or blank is an InputError naming the line."""
    rows = []
    seen = Instants()  # each instant's first (line, file)
    last: tuple[float, int] | None = None  # the latest stamp so far, and its line
    for i, line in plain_lines(read_text(path, "list"), path, "list"):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        parts = line.split()
        if len(parts) != n_fields:
            raise InputError(f"{path}:{i}: expected {n_fields} fields, got {len(parts)}")
        stamp = parse_stamp(parts[0], f"{path}:{i}")
        rel = PurePosixPath(parts[1])
        if rel.is_absolute() or ".." in rel.parts:
            raise InputError(f"{path}:{i}: {parts[1][:80]!r} points outside the dataset folder")
        first_stamp, (first, listed) = seen.setdefault(stamp, (i, parts[1]))
        if first != i:
            if listed != parts[1]:
                raise InputError(f"{path}:{i}: timestamp {parts[0]} "
                                 f"{same_instant_words(first_stamp, stamp)} line {first} with "
                                 f"another file ({parts[1][:80]!r}, not {listed[:80]!r})")
            continue
        if last is not None and stamp < last[0]:
            raise InputError(f"{path}:{i}: timestamp {parts[0]} is earlier than line {last[1]}'s;"
                             " the frames must be listed in time order")
        last = (stamp, i)
        rows.append(parts)
    return rows


def _nearest(times: np.ndarray, t: float) -> int | None:
    if len(times) == 0:
        return None
    i = int(np.argmin(np.abs(times - t)))
    return i if abs(times[i] - t) <= MAX_DT else None


def load_tum(root: Path) -> Dataset:
    root = Path(root)
    rgb = _read_list(root / "rgb.txt", 2)
    if not rgb:
        raise InputError(f"{root / 'rgb.txt'}: no images listed")
    depth = (_read_list(root / "depth.txt", 2)
             if optional_file(root / "depth.txt", "depth list") else [])
    gt = (read_tum_trajectory(root / "groundtruth.txt", numeric_stamps=True)
          if optional_file(root / "groundtruth.txt", "ground truth") else [])
    depth_t = np.array([float(r[0]) for r in depth])
    gt_t = np.array([float(stamp) for stamp, _ in gt])
    for listing, rows, key in (("rgb.txt", rgb, lambda rel: Path(rel).stem),
                               ("depth.txt", depth, lambda rel: rel)):
        seen: set[str] = set()
        for _, rel in rows:  # linear: a list of a million lines is checked in a second
            name = key(rel)
            if name in seen:  # one image at two instants: at most one of them is right
                raise InputError(f"{root / listing}: image {name[:80]!r} is listed more than "
                                 "once")
            seen.add(name)
    width, height = image_size(root / rgb[0][1])
    own = optional_file(root / "intrinsics.txt", "intrinsics")
    k = read_intrinsics(root / "intrinsics.txt") if own else None  # its errors name it
    try:
        if own:
            camera = Camera(width, height, k[0, 0], k[1, 1], k[0, 2], k[1, 2])
        else:  # the TUM RGB-D benchmark's default camera, for its 640x480 images
            camera = Camera(width, height, 525.0, 525.0, 319.5, 239.5)
    except InputError as err:
        if own:
            raise InputError(f"{root / 'intrinsics.txt'}: {err} (the images are "
                             f"{width}x{height})") from None
        raise InputError(f"{root / rgb[0][1]}: {err}: the default TUM camera (525 525 319.5 "
                         "239.5) is for 640x480 images; give intrinsics.txt") from None
    frames = []
    for stamp, rel in rgb:
        t = float(stamp)
        di, gi = _nearest(depth_t, t), _nearest(gt_t, t)
        depth_path = root / depth[di][1] if di is not None else None
        check_frame_files(root / rel, (width, height), depth_path, check_depth=True)
        frames.append(Frame(name=Path(rel).stem, image_path=root / rel, camera=camera,
                            depth_path=depth_path,
                            world_from_cam=gt[gi][1] if gi is not None else None,
                            sequence=root.name, timestamp=t))
    return Dataset(root, "tum", {root.name: frames}, depth_registered=True,
                   depth_units_per_metre=5000.0)
