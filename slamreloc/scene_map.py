"""The map folder: the regressor (what localization needs) plus the labelled training database.

    MAP/slamreloc_map.json   metadata: format version, the slamreloc version that wrote it,
                             feature and regressor configs, label/train stats, camera, and the
                             SHA-256 of the two array files below
    MAP/regressor.npz        regressor weights (float16) and output normalisation: plain arrays
    MAP/database.npz         labelled training descriptors (float16), their world points (m),
                             keypoints, frame index, training poses (world_from_cam 4x4) —
                             used by the matching baseline, pseudo-labelling and the viewer
    MAP/surface.npz          optional: the training frames' depth fused into points + normals
                             (map frame, m) — ICP refinement of relocalizations (surface.py)

Opening a map never runs code from it: both archives are read with numpy's
`allow_pickle=False` (an object array is refused), every array's shape, dtype and values are
checked against the metadata, and the metadata itself against a schema. A map of format
version 1 (weights in `regressor.pt`, a torch pickle) is still read, through torch's
weights-only unpickler, which refuses anything but tensors. A map from a newer format is
refused with a message naming both versions.

Writing is crash-safe: the new map is written into `.NAME.tmp-PID` beside MAP and swapped in
with one atomic `renameat2(RENAME_EXCHANGE)` (two renames where the file system lacks it; a
crash between them is rolled back at the next start). A writer holds an exclusive lock on
`.NAME.lock` (removed when it is done; `build_map` and `update_map` take it at their start);
a second writer fails at once. Leftovers of a killed writer are removed at the
next save or load of that map.
"""

from __future__ import annotations

import ctypes
import errno
import fcntl
import hashlib
import json
import math
import os
import shutil
import time
import zipfile
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field, fields
from functools import cached_property
from pathlib import Path

import numpy as np
import torch

from slamreloc import __version__
from slamreloc.errors import InputError
from slamreloc.regressor.model import RegressorConfig, SceneCoordinateRegressor
from slamreloc.surface import Surface
from slamreloc.types import Camera

MAP_FORMAT = "slamreloc-map"
FORMAT_VERSION = 2  # 1: regressor.pt (torch pickle); 2: regressor.npz + checksums
META, WEIGHTS, DATABASE = "slamreloc_map.json", "regressor.npz", "database.npz"
SURFACE = "surface.npz"  # optional
LEGACY_WEIGHTS = "regressor.pt"  # format 1
MAX_META_BYTES = 64 << 20
MAX_ARRAY_BYTES = 16 << 30
_BF16 = "::bfloat16"  # npz key suffix: a bfloat16 tensor stored as its int16 bits
DB_KEYS = ("descriptors", "points", "keypoints", "frame_index", "world_from_cam")


@dataclass
class MapDatabase:
    descriptors: np.ndarray  # (M, D) float16, labelled training descriptors
    points: np.ndarray  # (M, 3) float32 world points, metres
    keypoints: np.ndarray  # (M, 2) float32 pixels
    frame_index: np.ndarray  # (M,) int32 into frame_names
    frame_names: list[str] = field(default_factory=list)
    world_from_cam: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4)))


@dataclass
class SceneMap:
    root: Path
    meta: dict
    regressor: SceneCoordinateRegressor

    @staticmethod
    def is_map(path: Path) -> bool:
        return (Path(path) / META).is_file()

    @staticmethod
    def load(path: str | Path) -> SceneMap:
        """Read and check a map folder; any defect raises InputError naming the file."""
        root = Path(path)
        _clean_leftovers(root)
        if not root.is_dir():
            raise InputError(f"{root}: map folder not found")
        if not SceneMap.is_map(root):
            raise InputError(f"{root}: not a slamreloc map (no {META})")
        meta = read_meta(root)
        cfg = RegressorConfig.from_dict(meta["regressor"]["config"])
        if meta["format_version"] == 1:
            state = _read_legacy_weights(root / LEGACY_WEIGHTS)
        else:
            _check_digest(root, WEIGHTS, meta)
            state = _read_weights(root / WEIGHTS)
        return SceneMap(root, meta, _build_regressor(cfg, state, root / _weights_name(meta)))

    @property
    def camera(self) -> Camera:
        return Camera(**self.meta["camera"])

    @property
    def format_version(self) -> int:
        return self.meta["format_version"]

    @cached_property
    def database(self) -> MapDatabase:
        path = self.root / DATABASE
        if not path.is_file():
            raise InputError(f"{path}: map has no training database")
        if self.format_version >= 2:
            _check_digest(self.root, DATABASE, self.meta)
        arrays = _read_npz(path, "training database")
        return _check_database(arrays, path, self.regressor.config.in_dim,
                               list(self.meta.get("frame_names", [])))

    @cached_property
    def surface(self) -> Surface | None:
        """The fused depth surface, or None for a map built without depth."""
        if SURFACE not in self.meta.get("files", {}):
            return None
        path = self.root / SURFACE
        if not path.is_file():
            raise InputError(f"{path}: the map lists a surface but the file is missing")
        _check_digest(self.root, SURFACE, self.meta)
        return Surface.from_arrays(_read_npz(path, "surface"), str(path))

    def size_bytes(self) -> int:
        """What localization with the regressor needs: weights + metadata."""
        return ((self.root / _weights_name(self.meta)).stat().st_size
                + (self.root / META).stat().st_size)

    def database_bytes(self) -> int:
        return (self.root / DATABASE).stat().st_size


# ---------------------------------------------------------------------------------------------
# reading and checking


def read_meta(root: Path) -> dict:
    """slamreloc_map.json, checked against the schema; `format_version` is always set."""
    path = Path(root) / META
    try:
        size = path.stat().st_size
        if size > MAX_META_BYTES:
            raise InputError(f"{path}: {size} bytes, too large for map metadata")
        meta = json.loads(path.read_bytes())
    except (ValueError, RecursionError) as err:  # JSONDecodeError, UnicodeDecodeError
        raise InputError(f"{path}: not valid JSON ({_one_line(err)})") from None
    except OSError as err:
        raise InputError(f"{path}: cannot read ({err.strerror or err})") from None
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
        if not math.isfinite(need(cam, key, float, "camera.")):
            raise InputError(f"{path}: 'camera.{key}' must be finite, got {cam[key]}")
    if cam["fx"] <= 0 or cam["fy"] <= 0:
        raise InputError(f"{path}: camera focal lengths must be positive")
    extra = set(cam) - {"width", "height", "fx", "fy", "cx", "cy"}
    if extra:
        raise InputError(f"{path}: unknown camera key '{sorted(extra)[0]}'")
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


def _weights_name(meta: dict) -> str:
    return LEGACY_WEIGHTS if meta["format_version"] == 1 else WEIGHTS


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _check_digest(root: Path, name: str, meta: dict) -> None:
    path = root / name
    try:
        digest = _sha256(path)
    except OSError as err:
        raise InputError(f"{path}: cannot read ({err.strerror or err})") from None
    if digest != meta["files"][name]:
        raise InputError(f"{path}: contents do not match the checksum in {META} (the file is "
                         "corrupted, comes from another map, or the map was replaced while in "
                         "use)")


def _read_npz(path: Path, what: str) -> dict[str, np.ndarray]:
    """All arrays of an .npz archive, without unpickling anything."""
    try:
        size = path.stat().st_size
        with zipfile.ZipFile(path) as zf:  # refuse compression bombs before numpy reads
            for info in zf.infolist():
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
        raise InputError(f"{path}: not a readable {what} ({_one_line(err)})") from None
    except Exception as err:  # noqa: BLE001 - numpy's and zipfile's parsers raise many kinds
        # (BadZipFile, EOFError, KeyError, tokenize.TokenError, SyntaxError, MemoryError...)
        # on a damaged archive: all of them mean "this file is not readable"
        raise InputError(f"{path}: not a readable {what} ({type(err).__name__}: "
                         f"{_one_line(err)[:200]})") from None


def _read_weights(path: Path) -> dict[str, torch.Tensor]:
    arrays = _read_npz(path, "regressor weights")
    state = {}
    for key, arr in arrays.items():
        if key.endswith(_BF16):
            if arr.dtype != np.int16:
                raise InputError(f"{path}: {key} must hold int16 bits of bfloat16 values")
            state[key[: -len(_BF16)]] = torch.from_numpy(arr.copy()).view(torch.bfloat16)
        elif arr.dtype.kind in "fiub":
            state[key] = torch.from_numpy(arr.copy())
        else:
            raise InputError(f"{path}: {key} has dtype {arr.dtype}; weights must be numbers")
    return state


def _read_legacy_weights(path: Path) -> dict[str, torch.Tensor]:
    """Format 1: a torch zip archive of tensors, read with the weights-only unpickler."""
    if not path.is_file():
        raise InputError(f"{path}: map has no regressor weights")
    if tuple(int(p) for p in torch.__version__.split(".")[:2]) < (2, 6):
        raise InputError(f"{path}: reading a format-1 map safely needs torch >= 2.6 "
                         f"(have {torch.__version__}); re-create the map")
    if not zipfile.is_zipfile(path):
        raise InputError(f"{path}: not a torch weights archive (format-1 maps store a zip)")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # noqa: BLE001 - any failure of torch's unpickler means: refuse
        kind = ("refused: it holds Python objects other than tensors, which could run code"
                if "weights_only" in str(err) or "Unpickl" in type(err).__name__ else
                "not a readable torch weights archive")
        raise InputError(f"{path}: {kind} ({type(err).__name__}: "
                         f"{_one_line(err)[:200]})") from None
    if not isinstance(state, dict) or not all(
            isinstance(k, str) and isinstance(v, torch.Tensor) for k, v in state.items()):
        raise InputError(f"{path}: expected a dict of named tensors")
    return state


def _build_regressor(cfg: RegressorConfig, state: dict[str, torch.Tensor],
                     path: Path) -> SceneCoordinateRegressor:
    """Check the weights against the config (on the meta device: no memory is allocated for
    a config that a corrupted file blew up), then build the model."""
    with torch.device("meta"):
        expected = {k: tuple(v.shape) for k, v in SceneCoordinateRegressor(cfg).state_dict().items()}
    missing = sorted(set(expected) - set(state))
    extra = sorted(set(state) - set(expected))
    if missing or extra:
        what = f"missing {missing[0]}" if missing else f"unexpected {extra[0]}"
        raise InputError(f"{path}: weights do not fit the regressor config ({what})")
    for key, shape in expected.items():
        tensor = state[key]
        if tuple(tensor.shape) != shape:
            raise InputError(f"{path}: {key} has shape {tuple(tensor.shape)}, the config says "
                             f"{shape}")
        if not tensor.is_floating_point():
            raise InputError(f"{path}: {key} has dtype {tensor.dtype}, expected floats")
        if not bool(torch.isfinite(tensor).all()):
            raise InputError(f"{path}: {key} holds NaN or infinite values")
    model = SceneCoordinateRegressor(cfg)
    model.load_state_dict({k: v.float() for k, v in state.items()})
    return model.eval()


def _check_database(arrays: dict[str, np.ndarray], path: Path, dim: int,
                    frame_names: list[str]) -> MapDatabase:
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
    return MapDatabase(desc, pts, kps, idx, frame_names, poses)


def _is_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _short(v) -> str:
    text = repr(v)
    return text if len(text) <= 60 else text[:57] + "..."


def _one_line(err: BaseException) -> str:
    return " ".join(str(err).split()) or type(err).__name__


# ---------------------------------------------------------------------------------------------
# writing: lock, temporary sibling, atomic swap, clean-up of a killed writer's leftovers

_HELD: set[str] = set()  # maps whose write lock this process holds


def _lock_path(out: Path) -> Path:
    return out.parent / f".{out.name}.lock"


def _leftovers(out: Path) -> list[Path]:
    if not out.parent.is_dir():
        return []
    return sorted([*out.parent.glob(f".{out.name}.tmp-*"), *out.parent.glob(f".{out.name}.old-*")])


@contextmanager
def map_write_lock(out: str | Path) -> Iterator[None]:
    """Hold the exclusive write lock of map folder `out` (re-entrant within a process).

    A second process asking for it gets InputError at once. On entry, the leftovers of a
    killed writer are cleaned up (and a map it had moved aside is put back)."""
    out = Path(out)
    key = os.path.abspath(out)
    if key in _HELD:
        yield
        return
    out.parent.mkdir(parents=True, exist_ok=True)
    lock = _lock_path(out)
    while True:
        fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 32, 0).decode(errors="replace").strip() or "?"
            os.close(fd)
            raise InputError(f"{out}: another process (pid {holder}) is writing this map; "
                             "try again when it has finished") from None
        # the holder before us removes the lock file on release: make sure ours is the
        # file at the path, not one it has just unlinked
        try:
            same = os.path.samestat(os.fstat(fd), os.stat(lock))
        except FileNotFoundError:
            same = False
        if same:
            break
        os.close(fd)
    try:
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        _HELD.add(key)
        try:
            _recover(out)
            yield
        finally:
            _HELD.discard(key)
            lock.unlink(missing_ok=True)  # while still holding it (see above)
    finally:
        os.close(fd)  # releases the lock


def _recover(out: Path) -> None:
    """Under the lock: put back a map a killed writer had moved aside; remove its leftovers."""
    olds = [p for p in _leftovers(out) if ".old-" in p.name and SceneMap.is_map(p)]
    if olds and not out.exists():
        newest = max(olds, key=lambda p: p.stat().st_mtime)
        os.replace(newest, out)
        _fsync_dir(out.parent)
    for p in _leftovers(out):
        shutil.rmtree(p, ignore_errors=True) if p.is_dir() else p.unlink(missing_ok=True)


def _clean_leftovers(root: Path, wait_s: float = 10.0) -> None:
    """For readers: if a killed writer left debris beside `root`, clean it (best effort)."""
    if not _leftovers(root):
        return
    deadline = time.monotonic() + wait_s
    while True:
        try:
            with map_write_lock(root):
                return
        except InputError:  # a live writer: it cleans up itself; wait if the map is moved
            if root.exists() or time.monotonic() > deadline:
                return
            time.sleep(0.05)
        except OSError:  # read-only location: nothing to do
            return


def check_map_target(out: Path) -> None:
    """Raise unless `out` is absent, an empty folder, or a slamreloc map (to be replaced)."""
    out = Path(out)
    if out.exists() and (not out.is_dir() or (any(out.iterdir()) and not SceneMap.is_map(out))):
        raise InputError(f"{out}: exists and is not a slamreloc map; refusing to overwrite it")


def _crash_point(name: str) -> None:
    """Test hook: SLAMRELOC_TEST_CRASH_AT=name kills this process here (as kill -9 would)."""
    if os.environ.get("SLAMRELOC_TEST_CRASH_AT") == name:
        os.kill(os.getpid(), 9)


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _write_npz(path: Path, arrays: dict[str, np.ndarray]) -> str:
    with open(path, "wb") as f:
        np.savez(f, **arrays)
        f.flush()
        os.fsync(f.fileno())
    return _sha256(path)


def _state_arrays(model: SceneCoordinateRegressor) -> dict[str, np.ndarray]:
    arrays = {}
    for key, v in model.state_dict().items():
        v = v.detach().cpu()
        if v.is_floating_point() and v.dim() > 0 and key.startswith("mlp"):
            v = v.half()
        if v.dtype == torch.bfloat16:
            arrays[key + _BF16] = v.view(torch.int16).numpy()
        else:
            arrays[key] = v.numpy()
    return arrays


_RENAME_EXCHANGE = 2
_AT_FDCWD = -100


def _exchange(a: Path, b: Path) -> bool:
    """Atomically swap two paths (Linux renameat2 RENAME_EXCHANGE); False if unsupported."""
    if os.environ.get("SLAMRELOC_NO_RENAME_EXCHANGE"):
        return False
    try:
        fn = ctypes.CDLL(None, use_errno=True).renameat2
    except (OSError, AttributeError):
        return False
    fn.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    if fn(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE) == 0:
        return True
    err = ctypes.get_errno()
    if err in (errno.ENOSYS, errno.EINVAL, errno.EOPNOTSUPP, errno.ENOTSUP):
        return False
    raise OSError(err, os.strerror(err), str(b))


def _swap_in(tmp: Path, out: Path) -> None:
    """Make the complete map `tmp` appear at `out`; `out`'s old contents end at `tmp` (or an
    .old sibling) to be removed. At every instant `out` is a complete map, except in the
    two-rename fallback, whose gap `_recover` repairs."""
    if not out.exists():
        os.replace(tmp, out)
    elif not _exchange(tmp, out):
        old = out.parent / f".{out.name}.old-{os.getpid()}"
        os.replace(out, old)
        _crash_point("between-renames")
        os.replace(tmp, out)
        _fsync_dir(out.parent)
        shutil.rmtree(old, ignore_errors=True)
    _fsync_dir(out.parent)


def save_map(out: str | Path, meta: dict, model: SceneCoordinateRegressor, db: MapDatabase,
             extra: dict[str, dict[str, np.ndarray]] | None = None) -> Path:
    """Write a map atomically: into a temporary sibling folder, then swap it in for `out`.
    `extra`: more array files (name -> arrays, no pickle) written into the map with it.

    Refuses to replace an existing non-empty folder that is not a slamreloc map, and fails at
    once if another process is writing `out`."""
    out = Path(out)
    with map_write_lock(out):
        check_map_target(out)
        tmp = out.parent / f".{out.name}.tmp-{os.getpid()}"
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.mkdir(parents=True)
        try:
            files = {
                WEIGHTS: _write_npz(tmp / WEIGHTS, _state_arrays(model)),
                DATABASE: _write_npz(tmp / DATABASE, {
                    "descriptors": db.descriptors.astype(np.float16),
                    "points": db.points.astype(np.float32),
                    "keypoints": db.keypoints.astype(np.float32),
                    "frame_index": db.frame_index.astype(np.int32),
                    "world_from_cam": np.asarray(db.world_from_cam, np.float64)}),
            }
            for name, arrays in (extra or {}).items():
                files[name] = _write_npz(tmp / name, arrays)
            _crash_point("files-written")
            body = {k: v for k, v in meta.items() if k not in (
                "format", "version", "format_version", "slamreloc_version", "files",
                "frame_names")}
            full = {"format": MAP_FORMAT, "format_version": FORMAT_VERSION,
                    "slamreloc_version": __version__, **body, "files": files,
                    "frame_names": list(db.frame_names)}
            with open(tmp / META, "w") as f:
                f.write(json.dumps(full, indent=1))
                f.flush()
                os.fsync(f.fileno())
            _fsync_dir(tmp)
            _crash_point("before-swap")
            _swap_in(tmp, out)
            _crash_point("after-swap")
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
    return out


def migrate_map(path: str | Path) -> Path:
    """Rewrite an older-format map in place in the current format (atomically)."""
    old = SceneMap.load(path)
    if old.format_version == FORMAT_VERSION:
        return old.root
    return save_map(old.root, old.meta, old.regressor, old.database)
