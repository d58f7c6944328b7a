"""The on-disk format of a map folder: its file names and the checked, pickle-free readers of
its arrays (the metadata's schema is meta.py's `MapMeta`).

    MAP/slamreloc_map.json   metadata: format version, the slamreloc version that wrote it,
                             feature and regressor configs, label/train stats, camera, and the
                             SHA-256 of every array file below
    MAP/regressor.npz        regressor weights (float16) and output normalisation: plain arrays
    MAP/database.npz         labelled training descriptors (float16), their world points (m),
                             keypoints, frame index, training poses (world_from_cam 4x4) -
                             used by the matching baseline, pseudo-labelling and the viewer
    MAP/surface.npz          optional: the training frames' depth fused into points + normals
                             (map frame, m) - ICP refinement of relocalizations (surface.py)
    MAP/provenance.npz       optional, written by a map update (pseudo-labelling): per database
                             row `source` (int8: LABELLED, PSEUDO or NEW below) and `quality`
                             (float32 training weight in 0..1)

Opening a map never runs code from it: every archive is read with numpy's
`allow_pickle=False` (an object array is refused), every array's shape, dtype and values are
checked against the metadata, and the metadata itself against a schema. A map of format
version 1 (weights in `regressor.pt`, a torch pickle) is still read, through torch's
weights-only unpickler, which refuses anything but tensors. A map from a newer format is
refused with a message naming both versions.
"""

from __future__ import annotations

import errno
import os
import stat
import zipfile
from collections.abc import Mapping
from pathlib import Path
from typing import BinaryIO

import numpy as np

from slamreloc.errors import InputError
from slamreloc.geometry import MAX_COORDINATE
from slamreloc.io.fileio import open_regular, regular_size, sha256_of
from slamreloc.types import MAX_INTRINSIC

MAP_FORMAT = "slamreloc-map"
FORMAT_VERSION = 2  # 1: regressor.pt (torch pickle); 2: regressor.npz + checksums
META, WEIGHTS, DATABASE = "slamreloc_map.json", "regressor.npz", "database.npz"
SURFACE = "surface.npz"  # optional
PROVENANCE = "provenance.npz"  # optional: written by a map update
LEGACY_WEIGHTS = "regressor.pt"  # format 1
# every file a map folder holds (its writer's; `files` in the metadata names those of them
# it checksums)
MAP_FILES = frozenset({META, WEIGHTS, DATABASE, SURFACE, PROVENANCE, LEGACY_WEIGHTS})


def is_map_file(entry: os.DirEntry) -> bool:
    """Whether a folder's entry is a file a map writer writes (a regular file, not a link, of
    one of MAP_FILES' names)."""
    return entry.name in MAP_FILES and entry.is_file(follow_symlinks=False)
LABELLED, PSEUDO, NEW = 0, 1, 2  # provenance `source` of a database row: labelled when the map
# was built, a map label inherited by a registered frame (pseudo-label), triangulated anew
MAX_ARRAY_BYTES = 16 << 30
DB_KEYS = ("descriptors", "points", "keypoints", "frame_index", "world_from_cam")


def is_map(path: str | Path) -> bool:
    return (Path(path) / META).is_file()


def entry_kind(path: Path) -> str:
    """What is at `path` (symbolic links followed), in words: "missing", "a folder", "a
    regular file", "a named pipe", "a device", "a socket", "a symbolic link loop", "a
    dangling symbolic link", or "unreadable (REASON)"."""
    try:
        mode = path.stat().st_mode
    except FileNotFoundError:
        return "a dangling symbolic link" if path.is_symlink() else "missing"
    except OSError as err:
        return ("a symbolic link loop" if err.errno == errno.ELOOP
                else f"unreadable ({err.strerror or err})")
    return ("a folder" if stat.S_ISDIR(mode) else "a regular file" if stat.S_ISREG(mode)
            else "a named pipe" if stat.S_ISFIFO(mode)
            else "a device" if stat.S_ISCHR(mode) or stat.S_ISBLK(mode)
            else "a socket" if stat.S_ISSOCK(mode) else "not a file")


def map_folder_problem(path: str | Path) -> str | None:
    """Why `path` is not a map folder, saying what is there instead ("not a slamreloc map (map
    folder not found)", "...: a regular file is there, not a folder", "...: slamreloc_map.json
    is not a regular file (a named pipe)"); None for a folder holding a regular metadata
    file."""
    path = Path(path)
    kind = entry_kind(path)
    if kind == "missing":
        return "not a slamreloc map (map folder not found)"
    if kind != "a folder":
        return f"not a slamreloc map: {kind} is there, not a folder"
    meta = entry_kind(path / META)
    if meta == "missing":
        return f"not a slamreloc map (no {META})"
    if meta != "a regular file":
        return f"not a slamreloc map: {META} is not a regular file ({meta})"
    return None


def check_is_map(path: str | Path) -> None:
    """InputError unless `path` is a map folder (it holds the metadata file), saying what is
    there instead (`map_folder_problem`)."""
    problem = map_folder_problem(path)
    if problem:
        raise InputError(f"{path}: {problem}")


def sha256_file(path: Path, what: str = "map file") -> str:
    """SHA-256 of a regular file (InputError for a pipe, a device, a folder; see
    `open_regular`)."""
    with open_regular(path, what) as f:
        return _digest(f, path, what)


def _digest(f: BinaryIO, path: Path, what: str) -> str:
    """SHA-256 of an opened map file to its end; InputError naming it on a read error, or
    before a byte is read when it is larger than any map file (MAX_ARRAY_BYTES: a 60 GB
    sparse file would hold a reload, and a server's stop, for minutes)."""
    size = regular_size(f)
    if size > MAX_ARRAY_BYTES:
        raise InputError(f"{path}: {size} bytes, more than a map's {what} holds (at most "
                         f"{MAX_ARRAY_BYTES >> 30} GiB); refusing to read it")
    try:
        return sha256_of(f)
    except OSError as err:
        raise InputError(f"{path}: cannot read {what} ({err.strerror or err})") from None


class ChecksumMismatch(InputError):
    """A map file whose bytes are not the ones its metadata lists (`SceneMap` tells a map
    replaced while it was read from a damaged one)."""


def _mismatch(path: Path) -> ChecksumMismatch:
    return ChecksumMismatch(f"{path}: contents do not match the checksum in {META} (the file "
                            "is corrupted, comes from another map, or the map was replaced "
                            "while in use)")


def check_digest(root: Path, name: str, files: Mapping[str, str]) -> str:
    """The SHA-256 of `root/name`; InputError unless it is the one `files` (the metadata's)
    lists for it."""
    path = root / name
    digest = sha256_file(path)
    if digest != files[name]:
        raise _mismatch(path)
    return digest


def read_npz(path: Path, what: str, expected: str | None = None,
             digests: dict[str, str] | None = None, opened: BinaryIO | None = None
             ) -> dict[str, np.ndarray]:
    """All arrays of an .npz archive, without unpickling anything. The file is opened once
    (`open_regular`; or `opened`, `path` opened earlier, read from its start and closed): its
    SHA-256 is computed from the bytes that are then parsed, checked against `expected` when
    given, and recorded in `digests[path.name]` when given, so what is checked is what is
    read even if the folder is replaced meanwhile."""
    with opened or open_regular(path, what) as f:
        f.seek(0)
        digest = _digest(f, path, what)
        if expected is not None and digest != expected:
            raise _mismatch(path)
        if digests is not None:
            digests[path.name] = digest
        f.seek(0)
        return _parse_npz(f, path, what)


def _parse_npz(f: BinaryIO, path: Path, what: str) -> dict[str, np.ndarray]:
    try:
        size = regular_size(f)
        with zipfile.ZipFile(f) as zf:  # refuse compression bombs before numpy reads
            for info in zf.infolist():
                if not info.filename.endswith(".npy"):  # numpy would hand back raw bytes
                    raise InputError(f"{path}: member {info.filename[:80]!r} is not a numpy "
                                     "array (.npy); a map's archives hold arrays only")
                if info.file_size > MAX_ARRAY_BYTES or info.file_size > 100 * size + (1 << 20):
                    raise InputError(f"{path}: member {info.filename[:80]!r} claims "
                                     f"{info.file_size} bytes; refusing to read it")
        f.seek(0)
        with np.load(f, allow_pickle=False) as npz:  # values in this machine's byte order
            return {key: _native(npz[key]) for key in npz.files}
    except InputError:
        raise
    except ValueError as err:
        if "allow_pickle" in str(err) or "pickle" in str(err).lower():
            raise InputError(f"{path}: refused: the {what} holds pickled Python objects, "
                             "which could run code; a map holds plain arrays only") from None
        raise InputError(f"{path}: not a readable {what} ({one_line(err)[:200]})") from None
    except Exception as err:  # noqa: BLE001 - numpy's and zipfile's parsers raise many kinds
        # (BadZipFile, EOFError, KeyError, tokenize.TokenError, SyntaxError, MemoryError...)
        # on a damaged archive: all of them mean "this file is not readable"
        raise InputError(f"{path}: not a readable {what} ({type(err).__name__}: "
                         f"{one_line(err)[:200]})") from None


def _native(array: np.ndarray) -> np.ndarray:
    """`array` in native byte order (a big-endian archive holds the same values; torch and
    the checks below take native arrays only)."""
    return array if array.dtype.isnative else array.astype(array.dtype.newbyteorder("="))


def check_database(arrays: dict[str, np.ndarray], path: Path, dim: int,
                   frame_names: list[str] | None) -> None:
    """InputError unless database.npz's arrays (DB_KEYS) fit each other, the descriptor
    dimension and the frame names (None: the metadata has none, as an older map; a list,
    empty too, names every training pose), and the training poses are rigid."""
    missing = [k for k in DB_KEYS if k not in arrays]
    if missing:
        raise InputError(f"{path}: missing array '{missing[0]}'")
    desc, pts, kps, idx, poses = (arrays[k] for k in DB_KEYS)
    m = len(desc) if desc.ndim else -1

    def check(arr: np.ndarray, name: str, shape: tuple, kinds: str) -> None:
        if arr.ndim != len(shape) or any(s is not None and a != s
                                         for a, s in zip(arr.shape, shape)):
            want = "x".join("N" if s is None else str(s) for s in shape)
            raise InputError(f"{path}: '{name}' has shape {arr.shape}, expected {want}")
        if arr.dtype.kind not in kinds:
            raise InputError(f"{path}: '{name}' has dtype {arr.dtype}")
        if arr.dtype.kind == "f" and not np.isfinite(arr).all():
            raise InputError(f"{path}: '{name}' holds NaN or infinite values")

    check(desc, "descriptors", (None, dim), "f")
    check(pts, "points", (m, 3), "f")
    if len(pts) and np.abs(pts).max() > MAX_COORDINATE:
        raise InputError(f"{path}: 'points' beyond {MAX_COORDINATE:g} m")
    check(kps, "keypoints", (m, 2), "f")
    if len(kps) and np.abs(kps).max() > MAX_INTRINSIC:  # the pixel bound of a camera
        raise InputError(f"{path}: 'keypoints' beyond {MAX_INTRINSIC:g} pixels")
    check(idx, "frame_index", (m,), "iu")
    check(poses, "world_from_cam", (None, 4, 4), "f")
    if m == 0:
        raise InputError(f"{path}: the training database is empty")
    n_frames = len(poses)
    if idx.min() < 0 or idx.max() >= n_frames:
        raise InputError(f"{path}: 'frame_index' points outside the {n_frames} training poses")
    if frame_names is not None and len(frame_names) != n_frames:
        raise InputError(f"{path}: {n_frames} training poses but {len(frame_names)} frame "
                         f"names in {META}")
    rot = poses[:, :3, :3].astype(np.float64)
    ortho = np.abs(np.swapaxes(rot, 1, 2) @ rot - np.eye(3)).max(initial=0.0)
    if (ortho > 1e-3 or np.abs(poses[:, 3] - [0, 0, 0, 1]).max(initial=0.0) > 1e-6
            or (np.linalg.det(rot) <= 0).any()):  # a reflection is no rotation
        raise InputError(f"{path}: 'world_from_cam' holds matrices that are not rigid poses")
    if len(poses) and np.abs(poses[:, :3, 3]).max() > MAX_COORDINATE:  # `Rigid3`'s bound
        raise InputError(f"{path}: 'world_from_cam' places a camera beyond "
                         f"{MAX_COORDINATE:g} m")


def check_provenance(arrays: dict[str, np.ndarray], path: Path, n_rows: int) -> None:
    """InputError unless provenance.npz holds one `source` code (LABELLED, PSEUDO, NEW) and
    one finite `quality` per database row."""
    for key, kinds in (("source", "iu"), ("quality", "f")):
        if key not in arrays:
            raise InputError(f"{path}: missing array '{key}'")
        arr = arrays[key]
        if arr.shape != (n_rows,):
            raise InputError(f"{path}: '{key}' has shape {arr.shape}, expected the "
                             f"{n_rows} rows of the database")
        if arr.dtype.kind not in kinds:
            raise InputError(f"{path}: '{key}' has dtype {arr.dtype}")
    if not np.isin(arrays["source"], (LABELLED, PSEUDO, NEW)).all():
        raise InputError(f"{path}: 'source' holds codes other than {LABELLED}, {PSEUDO}, {NEW}")
    if not np.isfinite(arrays["quality"]).all():
        raise InputError(f"{path}: 'quality' holds NaN or infinite values")


def one_line(err: BaseException) -> str:
    """An exception's message on one line (for InputError messages)."""
    return " ".join(str(err).split()) or type(err).__name__
