"""The on-disk format of a map folder: its file names, the metadata schema, and the checked,
pickle-free readers of its arrays.

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

import hashlib
import math
import zipfile
from dataclasses import fields
from pathlib import Path

import numpy as np

from slamreloc import __version__
from slamreloc.camera_models import distortion_problem
from slamreloc.errors import InputError
from slamreloc.io.fileio import read_bytes
from slamreloc.geometry import MAX_COORDINATE
from slamreloc.io.jsonio import parse_json
from slamreloc.regressor.model import RegressorConfig
from slamreloc.types import camera_problem

MAP_FORMAT = "slamreloc-map"
FORMAT_VERSION = 2  # 1: regressor.pt (torch pickle); 2: regressor.npz + checksums
META, WEIGHTS, DATABASE = "slamreloc_map.json", "regressor.npz", "database.npz"
SURFACE = "surface.npz"  # optional
PROVENANCE = "provenance.npz"  # optional: written by a map update
LEGACY_WEIGHTS = "regressor.pt"  # format 1
LABELLED, PSEUDO, NEW = 0, 1, 2  # provenance `source` of a database row: labelled when the map
# was built, a map label inherited by a registered frame (pseudo-label), triangulated anew
MAX_META_BYTES = 64 << 20
MAX_ARRAY_BYTES = 16 << 30
DB_KEYS = ("descriptors", "points", "keypoints", "frame_index", "world_from_cam")


def is_map(path: str | Path) -> bool:
    return (Path(path) / META).is_file()


def check_is_map(path: str | Path) -> None:
    """InputError unless `path` is a map folder (it holds the metadata file)."""
    if not is_map(path):
        raise InputError(f"{path}: not a slamreloc map (no {META})")


def read_meta(root: Path) -> dict:
    """slamreloc_map.json, checked against the schema; `format_version` is always set."""
    path = Path(root) / META
    meta = parse_json(read_bytes(path, "map metadata", MAX_META_BYTES), path)
    if not isinstance(meta, dict):
        raise InputError(f"{path}: expected a JSON object, got {type(meta).__name__}")
    if meta.get("format") != MAP_FORMAT:
        raise InputError(f"{path}: not a slamreloc map (format={_short(meta.get('format'))})")
    version = meta.get("format_version", meta.get("version"))
    writer = meta.get("slamreloc_version")
    writer = writer if isinstance(writer, str) else "an unknown version"
    if not _is_int(version):
        raise InputError(f"{path}: format_version must be an integer, got {_short(version)}")
    if version > FORMAT_VERSION:
        raise InputError(f"{path}: map format version {version} (written by slamreloc "
                         f"{writer[:40]}) is newer than this slamreloc {__version__} reads "
                         f"(format versions 1 to {FORMAT_VERSION}); upgrade slamreloc")
    if version < 1:
        raise InputError(f"{path}: unknown map format version {version}")
    meta["format_version"] = version
    _check_schema(meta, path)
    return meta


def _check_schema(meta: dict, path: Path) -> None:
    def need(obj: dict, key: str, kind, where: str):
        if key not in obj:
            raise InputError(f"{path}: missing key '{where}{key}'")
        val = obj[key]
        ok = _is_int(val) if kind is int else (
            _is_number(val) if kind is float else isinstance(val, kind))
        if not ok:
            name = {int: "an integer", float: "a number", dict: "an object", str: "a string",
                    list: "a list", bool: "true or false"}[kind]
            raise InputError(f"{path}: '{where}{key}' must be {name}, got {_short(val)}")
        return val

    feats = need(meta, "features", dict, "")
    _check_feature_options(feats, path)
    reg = need(meta, "regressor", dict, "")
    need(reg, "arch", str, "regressor.")
    need(reg, "parameters", int, "regressor.")
    cfg = need(reg, "config", dict, "regressor.")
    _check_regressor_config(cfg, path)
    labels = need(meta, "labels", dict, "")
    if need(labels, "n_labelled", int, "labels.") < 0:
        raise InputError(f"{path}: 'labels.n_labelled' must not be negative")
    cam = need(meta, "camera", dict, "")
    for key in ("width", "height"):
        if not 0 < need(cam, key, int, "camera.") <= 1 << 16:
            raise InputError(f"{path}: 'camera.{key}' must be in 1..65536, got {cam[key]}")
    for key in ("fx", "fy", "cx", "cy"):
        need(cam, key, float, "camera.")
    problem = camera_problem(*(cam[k] for k in ("width", "height", "fx", "fy", "cx", "cy")))
    if problem:
        raise InputError(f"{path}: 'camera': {problem}")
    extra = set(cam) - {"width", "height", "fx", "fy", "cx", "cy", "model", "distortion"}
    if extra:
        raise InputError(f"{path}: unknown camera key '{sorted(extra)[0]}'")
    if "model" in cam or "distortion" in cam:
        model = need(cam, "model", str, "camera.")
        dist = need(cam, "distortion", list, "camera.")
        problem = distortion_problem(model, dist)
        if problem:
            raise InputError(f"{path}: 'camera': {problem}")
    names = meta.get("frame_names", [])
    if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
        raise InputError(f"{path}: 'frame_names' must be a list of strings")
    if meta["format_version"] >= 2:
        files = need(meta, "files", dict, "")
        for name in (WEIGHTS, DATABASE):
            digest = need(files, name, str, "files.")
            if len(digest) != 64 or any(c not in "0123456789abcdef" for c in digest):
                raise InputError(f"{path}: 'files.{name}' must be a SHA-256 hex digest")


def _check_feature_options(feats: dict, path: Path) -> None:
    from slamreloc.features.sift import SiftConfig

    name = feats.get("name")
    if name == "sift":
        config_cls = SiftConfig
    elif name == "superpoint":
        from slamreloc.features.superpoint import SuperPointConfig as config_cls
    else:
        raise InputError(f"{path}: 'features.name' must be sift or superpoint, got {_short(name)}")
    defaults = config_cls()
    for key, val in feats.items():
        if key == "name":
            continue
        known = {f.name for f in fields(config_cls)}
        if key not in known:
            raise InputError(f"{path}: unknown feature option 'features.{key}'")
        default = getattr(defaults, key)
        ok = (isinstance(val, bool) if isinstance(default, bool) else
              _is_int(val) if isinstance(default, int) else
              _is_number(val) and math.isfinite(val) if isinstance(default, float) else
              isinstance(val, type(default)))
        if not ok:
            raise InputError(f"{path}: 'features.{key}' has the wrong type ({_short(val)})")
    if _is_int(feats.get("max_keypoints")) and not 0 < feats["max_keypoints"] <= 1 << 20:
        raise InputError(f"{path}: 'features.max_keypoints' out of range")
    try:
        config_cls(**{k: v for k, v in feats.items() if k != "name"})  # the options' ranges
    except InputError as err:
        raise InputError(f"{path}: 'features': {err}") from None


def _check_regressor_config(cfg: dict, path: Path) -> None:
    where = "regressor.config."
    known = {f.name for f in fields(RegressorConfig)}
    extra = set(cfg) - known
    if extra:
        raise InputError(f"{path}: unknown key '{where}{sorted(extra)[0]}'")
    for key in ("in_dim", "hidden"):
        if key not in cfg:
            raise InputError(f"{path}: missing key '{where}{key}'")
    if not _is_int(cfg["in_dim"]) or not 0 < cfg["in_dim"] <= 4096:
        raise InputError(f"{path}: '{where}in_dim' must be an integer in 1..4096")
    hidden = cfg["hidden"]
    if (not isinstance(hidden, list) or not 0 < len(hidden) <= 32
            or not all(_is_int(h) and 0 < h <= 1 << 16 for h in hidden)):
        raise InputError(f"{path}: '{where}hidden' must be a list of 1..32 layer widths "
                         "in 1..65536")
    if cfg.get("head", "regression") not in ("regression", "clusters"):
        raise InputError(f"{path}: '{where}head' must be regression or clusters")
    n = cfg.get("n_clusters", 1)
    if not _is_int(n) or not 0 < n <= 1 << 16:
        raise InputError(f"{path}: '{where}n_clusters' must be an integer in 1..65536")
    if not isinstance(cfg.get("prototype_init", True), bool):
        raise InputError(f"{path}: '{where}prototype_init' must be true or false")
    thr = cfg.get("prototype_threshold", 0.0)
    if not _is_number(thr) or not math.isfinite(thr):
        raise InputError(f"{path}: '{where}prototype_threshold' must be a finite number")


def weights_name(meta: dict) -> str:
    """The regressor's file in a map of this metadata's format version."""
    return LEGACY_WEIGHTS if meta["format_version"] == 1 else WEIGHTS


def sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def check_digest(root: Path, name: str, meta: dict) -> None:
    """InputError unless `root/name` has the SHA-256 that `meta['files']` lists for it."""
    path = root / name
    try:
        digest = sha256_file(path)
    except OSError as err:
        raise InputError(f"{path}: cannot read ({err.strerror or err})") from None
    if digest != meta["files"][name]:
        raise InputError(f"{path}: contents do not match the checksum in {META} (the file is "
                         "corrupted, comes from another map, or the map was replaced while in "
                         "use)")


def read_npz(path: Path, what: str) -> dict[str, np.ndarray]:
    """All arrays of an .npz archive, without unpickling anything."""
    try:
        size = path.stat().st_size
        with zipfile.ZipFile(path) as zf:  # refuse compression bombs before numpy reads
            for info in zf.infolist():
                if not info.filename.endswith(".npy"):  # numpy would hand back raw bytes
                    raise InputError(f"{path}: member {info.filename[:80]!r} is not a numpy "
                                     "array (.npy); a map's archives hold arrays only")
                if info.file_size > MAX_ARRAY_BYTES or info.file_size > 100 * size + (1 << 20):
                    raise InputError(f"{path}: member {info.filename!r} claims "
                                     f"{info.file_size} bytes; refusing to read it")
        with np.load(path, allow_pickle=False) as npz:
            return {key: npz[key] for key in npz.files}
    except InputError:
        raise
    except ValueError as err:
        if "allow_pickle" in str(err) or "pickle" in str(err).lower():
            raise InputError(f"{path}: refused: the {what} holds pickled Python objects, "
                             "which could run code; a map holds plain arrays only") from None
        raise InputError(f"{path}: not a readable {what} ({one_line(err)})") from None
    except Exception as err:  # noqa: BLE001 - numpy's and zipfile's parsers raise many kinds
        # (BadZipFile, EOFError, KeyError, tokenize.TokenError, SyntaxError, MemoryError...)
        # on a damaged archive: all of them mean "this file is not readable"
        raise InputError(f"{path}: not a readable {what} ({type(err).__name__}: "
                         f"{one_line(err)[:200]})") from None


def check_database(arrays: dict[str, np.ndarray], path: Path, dim: int,
                   frame_names: list[str]) -> None:
    """InputError unless database.npz's arrays (DB_KEYS) fit each other, the descriptor
    dimension and the frame names, and the training poses are rigid."""
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
    check(idx, "frame_index", (m,), "iu")
    check(poses, "world_from_cam", (None, 4, 4), "f")
    if m == 0:
        raise InputError(f"{path}: the training database is empty")
    n_frames = len(poses)
    if idx.min() < 0 or idx.max() >= n_frames:
        raise InputError(f"{path}: 'frame_index' points outside the {n_frames} training poses")
    if frame_names and len(frame_names) != n_frames:
        raise InputError(f"{path}: {n_frames} training poses but {len(frame_names)} frame "
                         f"names in {META}")
    rot = poses[:, :3, :3].astype(np.float64)
    ortho = np.abs(np.swapaxes(rot, 1, 2) @ rot - np.eye(3)).max(initial=0.0)
    if ortho > 1e-3 or np.abs(poses[:, 3] - [0, 0, 0, 1]).max(initial=0.0) > 1e-6:
        raise InputError(f"{path}: 'world_from_cam' holds matrices that are not rigid poses")


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


def _is_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _short(v) -> str:
    text = repr(v)
    return text if len(text) <= 60 else text[:57] + "..."


def one_line(err: BaseException) -> str:
    """An exception's message on one line (for InputError messages)."""
    return " ".join(str(err).split()) or type(err).__name__
