"""Fuzzing of everything slamreloc reads from disk (hypothesis, derandomized: the same cases
in every CI run).

Each test damages valid files (truncation, bit flips, garbage, NaN and huge numbers,
non-rigid and wrong-shape matrices, images of the wrong size or depth type, JSON of the wrong
type, missing keys, split files naming missing sequences, bad timestamps, COLMAP models
with truncated files, trusted counts, unknown camera models and missing images, ...) and runs the
public loaders on them. A case passes when the loader either works or raises InputError (the
CLI's one-line `error: <file>: <problem>`, exit 2); any other exception is a traceback for the
user and fails the test, as does a case that runs longer than the hang limit. The CLI itself
is fuzzed too, in process (`slamreloc.cli.main`, exit status and stderr checked).

Case counts are printed at the end of the pytest run ("fuzzing: N generated bad-input
cases") and written to `<pytest basetemp>/fuzz_counts.json`.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import struct
import tempfile
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

from slamreloc.datasets import load_dataset, read_depth, read_image, read_pose
from slamreloc.errors import InputError
from slamreloc.geometry import look_at, names_sidecar, read_tum_trajectory, tum_line
from slamreloc.regressor.model import RegressorConfig, SceneCoordinateRegressor
from slamreloc.map.format import DATABASE, META, WEIGHTS, sha256_file
from slamreloc.map.meta import CameraMeta, FeatureMeta, MapMeta, RegressorMeta
from slamreloc.map.write import save_map
from slamreloc.map.scene_map import MapDatabase, SceneMap
from tests import fuzzing
from tests.colmap_project import write_colmap_project
from tests.fuzzing import (COUNTS, damaged_bytes, damaged_json, damaged_text, fuzz_settings,
                           no_hang, run_cli)

# cases per test; CI must run at least BUDGET of them in all (test_fuzz_budget_ran counts)
PLANNED = {"sevenscenes": 400, "tum": 300, "colmap": 400, "pose": 300, "trajectory": 400,
           "view_trajectory": 200, "map_json": 250, "map_arrays": 250, "map_arrays_semantic": 100,
           "legacy_weights": 80, "cli": 40, "cli_colmap": 40}
BUDGET = 2000

# SLAMRELOC_FUZZ_SCALE=0.1 for a quick local run (and a budget scaled alike); CI runs the full one
SCALE = float(os.environ.get("SLAMRELOC_FUZZ_SCALE", "1"))
PLANNED = {k: max(1, int(v * SCALE)) for k, v in PLANNED.items()}


@pytest.fixture(scope="module", autouse=True)
def _write_counts(tmp_path_factory):
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # thousands of tiny models: threads only add overhead
    yield
    torch.set_num_threads(threads)
    path = tmp_path_factory.getbasetemp() / "fuzz_counts.json"
    path.write_text(json.dumps(fuzzing.summary(), indent=1))


@pytest.fixture(scope="module")
def work(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("fuzz")


def _case_dir(work: Path, base: Path) -> Path:
    """A copy of `base` made of hard links: cheap; damaged files are replaced, not edited."""
    dst = Path(tempfile.mkdtemp(dir=work)) / base.name
    shutil.copytree(base, dst, copy_function=os.link)
    return dst


def _record(fmt: str, outcome: str) -> None:
    COUNTS[(fmt, outcome)] += 1


def _run(fmt: str, fn) -> str:
    """Run a loader on a damaged input: it works, or raises InputError; nothing else."""
    with no_hang(30):
        try:
            fn()
            outcome = "loaded"
        except InputError as err:
            assert "\n" not in str(err)
            outcome = "refused"
    _record(fmt, outcome)
    return outcome


def _assert_ran(fmt: str) -> None:
    done = sum(n for (f, _), n in COUNTS.items() if f == fmt)
    assert done >= 0.9 * PLANNED[fmt], f"{fmt}: only {done} cases ran"


# --- datasets --------------------------------------------------------------------------------

K = np.array([[60.0, 0, 32], [0, 60.0, 24], [0, 0, 1]])


def _texture(rng, h=48, w=64) -> np.ndarray:
    return cv2.resize((rng.random((h // 4, w // 4, 3)) * 255).astype(np.uint8), (w, h),
                      interpolation=cv2.INTER_NEAREST)


@pytest.fixture(scope="module")
def seven_base(work) -> Path:
    return make_sevenscenes(work / "base7" / "ds")


def make_sevenscenes(root: Path) -> Path:
    """A 7-Scenes/synthetic-layout dataset: seq-01 PNG colour, seq-02 JPEG colour, registered
    16-bit depth, poses, splits, intrinsics and scene.json."""
    rng = np.random.default_rng(0)
    for s, ext in ((1, "png"), (2, "jpg")):
        d = root / f"seq-{s:02d}"
        d.mkdir(parents=True)
        for i in range(2):
            cv2.imwrite(str(d / f"frame-{i:06d}.color.{ext}"), _texture(rng))
            cv2.imwrite(str(d / f"frame-{i:06d}.depth.png"),
                        (rng.random((48, 64)) * 4000 + 500).astype(np.uint16))
            pose = look_at(np.array([0.1 * i, 0.05 * s, 1.0]), np.array([0.0, 2.0, 1.0]))
            np.savetxt(d / f"frame-{i:06d}.pose.txt", pose.matrix(), fmt="%.9f")
    (root / "TrainSplit.txt").write_text("sequence1\n")
    (root / "TestSplit.txt").write_text("sequence2\n")
    np.savetxt(root / "intrinsics.txt", K)
    (root / "scene.json").write_text(json.dumps({
        "generator": "test", "seed": 0, "depth_registered": True,
        "sequences": {"seq-01": "map", "seq-02": "query"}}))
    return root


@pytest.fixture(scope="module")
def tum_base(work, seven_base) -> Path:
    root = work / "basetum" / "tum"
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    rgb, depth, gt = ["# timestamp filename"], ["# timestamp filename"], ["# ground truth"]
    frames = load_dataset(seven_base).frames("seq-01")
    for i, f in enumerate(frames):
        t = 1305031102.175304 + i / 30
        shutil.copy(f.image_path, root / "rgb" / f"{t:.6f}.png")
        cv2.imwrite(str(root / "depth" / f"{t + 0.003:.6f}.png"),
                    (read_depth(f.depth_path) * 5000).astype(np.uint16))
        rgb.append(f"{t:.6f} rgb/{t:.6f}.png")
        depth.append(f"{t + 0.003:.6f} depth/{t + 0.003:.6f}.png")
        gt.append(tum_line(f"{t + 0.001:.4f}", f.world_from_cam))
    for name, lines in (("rgb.txt", rgb), ("depth.txt", depth), ("groundtruth.txt", gt)):
        (root / name).write_text("\n".join(lines) + "\n")
    return root


@st.composite
def reencoded_image(draw, path: Path) -> bytes:
    """A valid image of the wrong size, channel count or bit depth."""
    w, h = draw(st.sampled_from([(64, 48), (63, 48), (64, 47), (32, 24), (1, 1), (640, 480)]))
    kind = draw(st.sampled_from(["u8c3", "u8c1", "u16c1", "u16c3", "u8c4"]))
    dtype = np.uint16 if kind.startswith("u16") else np.uint8
    channels = int(kind[-1])
    shape = (h, w) if channels == 1 else (h, w, channels)
    img = np.full(shape, draw(st.integers(0, 255)), dtype)
    ext = draw(st.sampled_from([".png", path.suffix if path.suffix != ".txt" else ".png"]))
    if ext == ".jpg":
        img = img.astype(np.uint8)
    ok, buf = cv2.imencode(ext, img)
    assert ok
    return buf.tobytes()


@st.composite
def damaged_file(draw, root: Path, files: list[str]):
    """(relative path, new bytes or 'remove' / 'dir') for one file of the dataset."""
    rel = draw(st.sampled_from(files))
    structural = draw(st.sampled_from([None] * 18 + ["remove", "dir"]))
    if structural:
        return rel, structural
    path = root / rel
    data = path.read_bytes()
    if path.suffix == ".json":
        return rel, draw(damaged_json(json.loads(data)))
    if path.suffix == ".txt":
        return rel, draw(damaged_text(data.decode()))
    if draw(st.booleans()):
        return rel, draw(reencoded_image(path))
    return rel, draw(damaged_bytes(data))


def _apply(root: Path, rel: str, change) -> None:
    path = root / rel
    path.unlink()  # never write through a hard link into the base files
    if change == "dir":
        path.mkdir()
    elif change != "remove":
        path.write_bytes(change)


def _files(root: Path) -> list[str]:
    return sorted(str(p.relative_to(root)) for p in root.rglob("*") if p.is_file())


def _exercise_dataset(root: Path) -> None:
    ds = load_dataset(root)
    for split in ("train", "test", "all", "map", "query", "seq-01", "seq-02,seq-01", "x"):
        try:
            ds.frames(split)
        except InputError:
            pass
    for f in ds.frames("all"):
        img = read_image(f.image_path)
        # a dataset that loaded has images of its camera's size
        assert img.shape == (f.camera.height, f.camera.width, 3)
        if f.depth_path is not None and ds.depth_registered:
            depth = read_depth(f.depth_path, ds.depth_units_per_metre,
                               size=(img.shape[1], img.shape[0]))
            assert depth.shape == img.shape[:2] and np.isfinite(depth).all()
        if f.world_from_cam is not None:
            r = f.world_from_cam.rotation
            assert np.abs(r.T @ r - np.eye(3)).max() < 1e-6 and np.isfinite(
                f.world_from_cam.translation).all()


@fuzz_settings(PLANNED["sevenscenes"])
@given(data=st.data())
def test_fuzz_sevenscenes_dataset(seven_base, work, data):
    root = _case_dir(work, seven_base)
    files = _files(root)
    for _ in range(data.draw(st.sampled_from([1, 1, 1, 2]))):
        rel, change = data.draw(damaged_file(seven_base, files))
        if (root / rel).is_file():
            _apply(root, rel, change)
    _run("sevenscenes", lambda: _exercise_dataset(root))
    shutil.rmtree(root.parent)


def test_fuzz_sevenscenes_ran():
    _assert_ran("sevenscenes")


@fuzz_settings(PLANNED["tum"])
@given(data=st.data())
def test_fuzz_tum_dataset(tum_base, work, data):
    root = _case_dir(work, tum_base)
    files = _files(root)
    lists = [f for f in files if f.endswith(".txt")]
    # mostly the lists (timestamps, paths, poses); sometimes an image
    rel, change = data.draw(damaged_file(tum_base, lists if data.draw(st.integers(0, 3)) else
                                         files))
    _apply(root, rel, change)
    _run("tum", lambda: _exercise_dataset(root))
    shutil.rmtree(root.parent)


def test_fuzz_tum_ran():
    _assert_ran("tum")


COLMAP_BASES = {"bin": ("bin", False), "bin_legacy": ("bin", True), "txt": ("txt", False),
                "txt_legacy": ("txt", True)}


@pytest.fixture(scope="module")
def colmap_bases(work, seven_base) -> dict[str, Path]:
    """The 7-Scenes base's frames as COLMAP projects: binary and text models, with rigs and
    frames files (COLMAP >= 3.12) and without (older COLMAP)."""
    frames = load_dataset(seven_base).frames("all")
    bases = {key: write_colmap_project(frames, work / f"basecolmap_{key}" / "project", ext,
                                       legacy) for key, (ext, legacy) in COLMAP_BASES.items()}
    for root in bases.values():
        assert len(load_dataset(root).frames("train")) == len(frames)
    return bases


COLMAP_MODEL_NAMES = ["SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "OPENCV", "OPENCV_FISHEYE",
                      "FOV", "EQUIRECTANGULAR", "FOO", "pinhole", "PINHOLE PINHOLE", "1"]
HUGE_COUNTS = [0, 1, 2, 3, 255, 2 ** 31, 2 ** 32, 2 ** 40, 2 ** 63, 2 ** 64 - 1]


@st.composite
def damaged_colmap(draw, root: Path) -> list[tuple[str, object]]:
    """Changes to a COLMAP project: a damaged model file (bytes or text, removed), a count
    that pycolmap would trust, an unknown or distorted camera model, missing or damaged
    images, split files naming unknown sequences."""
    files = _files(root)
    model = [f for f in files if f.startswith("sparse/") and "points3D" not in f]  # unread
    images = [f for f in files if f.startswith("images/")]
    kind = draw(st.sampled_from(["model"] * 5 + ["count", "count", "camera_model",
                                                 "missing_image", "image", "split"]))
    if kind == "missing_image":
        return [(rel, "remove") for rel in draw(st.lists(st.sampled_from(images), min_size=1,
                                                         max_size=2, unique=True))]
    if kind == "image":
        return [draw(damaged_file(root, images))]
    if kind == "split":
        name = draw(st.sampled_from(["TrainSplit.txt", "TestSplit.txt"]))
        lines = draw(st.lists(st.sampled_from(["seq-01", "seq-02", "seq-03", "images", "", "#",
                                               "../seq-01", "seq-01,seq-02"]) | st.text(
                                                   max_size=10), max_size=4))
        return [(name, ("\n".join(lines) + "\n").encode("utf-8", "surrogatepass"))]
    rel = draw(st.sampled_from(model))
    data = (root / rel).read_bytes()
    binary = rel.endswith(".bin")
    if kind == "camera_model":
        rel = rel.rsplit("/", 1)[0] + ("/cameras.bin" if binary else "/cameras.txt")
        data = (root / rel).read_bytes()
        if binary:
            model_id = draw(st.sampled_from([-1, 2, 4, 5, 7, 17, 18, 19, 255, 2 ** 31 - 1]))
            return [(rel, data[:12] + struct.pack("<i", model_id) + data[16:])]
        words = data.decode().splitlines()[-1].split()
        words[1] = draw(st.sampled_from(COLMAP_MODEL_NAMES))
        return [(rel, (data.decode() + " ".join(words) + "\n").encode()
                 if draw(st.booleans()) else " ".join(words).encode())]
    if kind == "count" and binary and len(data) >= 8:
        # the file's own count, or an 8-byte field anywhere (points2D counts, ids, names)
        pos = 0 if draw(st.booleans()) else draw(st.integers(0, len(data) - 8))
        return [(rel, data[:pos] + struct.pack("<Q", draw(st.sampled_from(HUGE_COUNTS)))
                 + data[pos + 8:])]
    if draw(st.integers(0, 9)) == 0:
        return [(rel, draw(st.sampled_from(["remove", "dir"])))]
    return [(rel, draw(damaged_bytes(data)) if binary else draw(damaged_text(data.decode())))]


@fuzz_settings(PLANNED["colmap"])
@given(data=st.data(), base=st.sampled_from(sorted(COLMAP_BASES)))
def test_fuzz_colmap_project(colmap_bases, work, data, base):
    root = _case_dir(work, colmap_bases[base])
    for rel, change in data.draw(damaged_colmap(colmap_bases[base])):
        if (root / rel).is_file():
            _apply(root, rel, change)
        elif change not in ("remove", "dir"):
            (root / rel).write_bytes(change)
    _run("colmap", lambda: _exercise_dataset(root))
    shutil.rmtree(root.parent)


def test_fuzz_colmap_ran():
    _assert_ran("colmap")


finite_or_not = st.floats(allow_nan=True, allow_infinity=True, width=64)


@st.composite
def pose_matrices(draw):
    """4x4 (or wrong-shape) matrices: rigid, nearly rigid, scaled, reflected, NaN, huge."""
    rows, cols = draw(st.sampled_from([(4, 4)] * 6 + [(3, 4), (4, 3), (1, 16), (5, 4), (0, 0)]))
    if (rows, cols) == (4, 4) and draw(st.booleans()):
        angles = draw(st.lists(st.floats(-np.pi, np.pi), min_size=3, max_size=3))
        from slamreloc.geometry import axis_angle_to_matrix

        m = np.eye(4)
        m[:3, :3] = axis_angle_to_matrix(np.array(angles))
        m[:3, 3] = draw(st.lists(st.floats(-1e3, 1e3), min_size=3, max_size=3))
        i, j = draw(st.integers(0, 3)), draw(st.integers(0, 3))
        m[i, j] = draw(st.one_of(finite_or_not, st.sampled_from([
            m[i, j], m[i, j] + 1e-7, m[i, j] * 1.01, -m[i, j], m[i, j] + 1e-4])))
        return m
    return np.array(draw(st.lists(finite_or_not, min_size=rows * cols,
                                  max_size=rows * cols))).reshape(rows, cols)


@fuzz_settings(PLANNED["pose"])
@given(matrix=pose_matrices())
def test_fuzz_pose_files(work, matrix):
    path = Path(tempfile.mkdtemp(dir=work)) / "frame-000000.pose.txt"
    np.savetxt(path, matrix, fmt="%r") if matrix.size else path.write_text("")

    def check():
        pose = read_pose(path)
        assert np.isfinite(pose.matrix()).all()
        r = pose.rotation
        assert np.abs(r.T @ r - np.eye(3)).max() < 1e-6 and np.linalg.det(r) > 0

    _run("pose", check)
    shutil.rmtree(path.parent)


def test_fuzz_pose_ran():
    _assert_ran("pose")


TRAJECTORY = "".join(
    tum_line(f"{1.0 + i / 30:.6f}", look_at(np.array([0.1 * i, 0, 1.0]), np.array([0, 2.0, 1])))
    + "\n" for i in range(4))


@fuzz_settings(PLANNED["trajectory"])
@given(content=damaged_text("# trajectory\n" + TRAJECTORY), numeric=st.booleans())
def test_fuzz_tum_trajectory(work, content, numeric):
    path = Path(tempfile.mkdtemp(dir=work)) / "traj.txt"
    path.write_bytes(content)

    def check():
        for _, pose in read_tum_trajectory(path, numeric_stamps=numeric):
            assert np.isfinite(pose.matrix()).all()

    _run("trajectory", check)
    shutil.rmtree(path.parent)


def test_fuzz_trajectory_ran():
    _assert_ran("trajectory")


NAMES = "".join(f"{1.0 + i / 30:.6f} seq-02/frame-{i:06d}\n" for i in range(4))


@fuzz_settings(PLANNED["view_trajectory"])
@given(content=st.one_of(st.just(TRAJECTORY.encode()), damaged_text(TRAJECTORY)),
       names=st.one_of(st.none(), damaged_text(NAMES)))
def test_fuzz_view_trajectory(work, content, names):
    """`slamreloc view --trajectory T.txt`: the file and its `evaluate --trajectory` names sidecar."""
    from slamreloc.viewer.loaders import read_trajectory

    path = Path(tempfile.mkdtemp(dir=work)) / "poses.txt"
    path.write_bytes(content)
    if names is not None:
        names_sidecar(path).write_bytes(names)

    def check():
        traj = read_trajectory(path)
        assert len(traj.stamps) == len(traj.names) == len(traj) > 0
        assert np.isfinite(traj.stamps).all() and np.isfinite(traj.positions).all()

    _run("view_trajectory", check)
    shutil.rmtree(path.parent)


def test_fuzz_view_trajectory_ran():
    _assert_ran("view_trajectory")


# --- map files -------------------------------------------------------------------------------

IN_DIM = 128


def _tiny_map(out: Path, n: int = 64) -> Path:
    """A valid map of today's format with `n` database rows, small enough to copy per case
    (SIFT-sized input)."""
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    cfg = RegressorConfig(in_dim=IN_DIM, hidden=(16, 8), head="clusters", n_clusters=4)
    model = SceneCoordinateRegressor(cfg)
    poses = np.stack([look_at(np.array([0.1 * i, 0, 1.0]), np.array([0, 2.0, 1])).matrix()
                      for i in range(2)])
    db = MapDatabase(rng.random((n, IN_DIM)).astype(np.float32), rng.random((n, 3)),
                     rng.random((n, 2)) * 40, rng.integers(0, 2, n), ["seq-01/frame-000000",
                                                                       "seq-01/frame-000001"],
                     poses)
    meta = MapMeta(features=FeatureMeta("sift", {"max_keypoints": 512}),
                   regressor=RegressorMeta("tiny", cfg.to_dict(), model.num_parameters()),
                   labels={"n_labelled": n}, train={"epochs": 0},
                   camera=CameraMeta(64, 48, 60.0, 60.0, 32.0, 24.0))
    return save_map(out, meta, model, db)


@pytest.fixture(scope="module")
def map_base(work) -> Path:
    root = _tiny_map(work / "basemap" / "map")
    SceneMap.load(root).database  # noqa: B018 - the base map is valid
    return root


def _exercise_map(root: Path) -> None:
    m = SceneMap.load(root)
    m.camera  # noqa: B018
    with torch.no_grad():
        assert m.regressor(torch.zeros(3, m.regressor.config.in_dim)).shape == (3, 3)
    db = m.database
    assert db.descriptors.shape[1] == m.regressor.config.in_dim
    assert len(db.points) == len(db.descriptors) == len(db.frame_index) > 0


def _resign(root: Path, name: str) -> None:
    """Record the damaged file's checksum, so that the parsers behind the check are fuzzed."""
    meta = json.loads((root / META).read_text())
    meta["files"][name] = sha256_file(root / name)
    _apply(root, META, json.dumps(meta).encode())


@fuzz_settings(PLANNED["map_json"])
@given(data=st.data())
def test_fuzz_map_metadata(map_base, work, data):
    root = _case_dir(work, map_base)
    doc = json.loads((root / META).read_text())
    _apply(root, META, data.draw(damaged_json(doc)))
    _run("map_json", lambda: _exercise_map(root))
    shutil.rmtree(root.parent)


def test_fuzz_map_json_ran():
    _assert_ran("map_json")


@fuzz_settings(PLANNED["map_arrays"])
@given(data=st.data(), name=st.sampled_from([WEIGHTS, DATABASE]), resign=st.booleans())
def test_fuzz_map_array_files(map_base, work, data, name, resign):
    """Truncated / bit-flipped / garbage regressor.npz and database.npz, with the checksum in
    the metadata left (caught there) or updated (caught by the archive and array checks)."""
    root = _case_dir(work, map_base)
    _apply(root, name, data.draw(damaged_bytes((root / name).read_bytes())))
    if resign:
        _resign(root, name)
    _run("map_arrays", lambda: _exercise_map(root))
    shutil.rmtree(root.parent)


def test_fuzz_map_arrays_ran():
    _assert_ran("map_arrays")


class _Payload:
    """Unpickling this runs code (it would create the file `target`)."""

    def __init__(self, target: str) -> None:
        self.target = target

    def __reduce__(self):
        return (Path.touch, (Path(self.target),))


@st.composite
def damaged_arrays(draw, arrays: dict, target: str) -> dict:
    arrays = dict(arrays)
    key = draw(st.sampled_from(sorted(arrays)))
    a = arrays[key]
    kind = draw(st.sampled_from(["drop", "extra", "nan", "inf", "huge", "shape", "transpose",
                                 "dtype_int", "dtype_str", "dtype_complex", "object", "scalar",
                                 "empty", "index"]))
    if kind == "drop":
        del arrays[key]
    elif kind == "extra":
        arrays["extra"] = np.zeros(3)
    elif kind in ("nan", "inf", "huge") and a.dtype.kind == "f" and a.size:
        a = a.copy()
        a.flat[draw(st.integers(0, a.size - 1))] = {"nan": np.nan, "inf": np.inf,
                                                    "huge": 6e4}[kind]
        arrays[key] = a
    elif kind == "shape" and a.ndim:
        cut = draw(st.integers(0, max(a.shape[-1] - 1, 0)))
        arrays[key] = a[..., :cut]
    elif kind == "transpose":
        arrays[key] = a.T.copy()
    elif kind == "dtype_int":
        arrays[key] = a.astype(np.int64)
    elif kind == "dtype_str":
        arrays[key] = a.astype(str)
    elif kind == "dtype_complex":
        arrays[key] = a.astype(np.complex64)
    elif kind == "object":
        arrays[key] = np.array([_Payload(target)], dtype=object)
    elif kind == "scalar":
        arrays[key] = np.float32(1.0)
    elif kind == "empty":
        arrays[key] = a[:0] if a.ndim else np.zeros(0, a.dtype)
    elif kind == "index" and a.dtype.kind in "iu":
        arrays[key] = a + draw(st.sampled_from([-5, 2, 10 ** 6]))
    return arrays


@fuzz_settings(PLANNED["map_arrays_semantic"])
@given(data=st.data(), name=st.sampled_from([WEIGHTS, DATABASE]))
def test_fuzz_map_array_contents(map_base, work, data, name):
    """Well-formed archives with wrong contents: missing/extra arrays, NaN, wrong shapes and
    dtypes, pickled objects (that would create a file if unpickled), bad indices."""
    root = _case_dir(work, map_base)
    target = root.parent / "payload-ran"
    with np.load(root / name) as z:
        arrays = {k: z[k] for k in z.files}
    arrays = data.draw(damaged_arrays(arrays, str(target)))
    (root / name).unlink()
    with open(root / name, "wb") as f:
        np.savez(f, **arrays)
    _resign(root, name)
    _run("map_arrays_semantic", lambda: _exercise_map(root))
    assert not target.exists(), "a pickle payload in a map file was executed"
    shutil.rmtree(root.parent)


def test_fuzz_map_arrays_semantic_ran():
    _assert_ran("map_arrays_semantic")


@pytest.fixture(scope="module")
def legacy_base(work, map_base) -> Path:
    """The base map rewritten in format 1 (weights in regressor.pt via torch.save)."""
    root = work / "baselegacy" / "map"
    root.mkdir(parents=True)
    m = SceneMap.load(map_base)
    state = {k: (v.half() if v.is_floating_point() and v.dim() > 0 and k.startswith("mlp")
                 else v) for k, v in m.regressor.state_dict().items()}
    torch.save(state, root / "regressor.pt")
    shutil.copy(map_base / DATABASE, root / DATABASE)
    meta = {k: v for k, v in m.meta.items()
            if k not in ("format_version", "slamreloc_version", "files")}
    (root / META).write_text(json.dumps({**meta, "version": 1}))
    assert SceneMap.load(root).format_version == 1
    return root


@fuzz_settings(PLANNED["legacy_weights"])
@given(data=st.data())
def test_fuzz_legacy_torch_weights(legacy_base, work, data):
    root = _case_dir(work, legacy_base)
    path = root / "regressor.pt"
    _apply(root, "regressor.pt", data.draw(damaged_bytes(path.read_bytes())))
    _run("legacy_weights", lambda: _exercise_map(root))
    shutil.rmtree(root.parent)


def test_fuzz_legacy_weights_ran():
    _assert_ran("legacy_weights")


# --- the command line, in process --------------------------------------------------------------

def _cli(argv: list[str]) -> tuple[int, str]:
    return run_cli(argv, 60)


def check_cli_outcome(code: int, stderr: str, fmt: str) -> None:
    """Exit 0, or exit 2 with exactly one `error: <file>: <problem>` line, last; never a
    traceback."""
    assert "Traceback" not in stderr
    assert code in (0, 2), (code, stderr)
    if code == 2:
        lines = [ln for ln in stderr.splitlines() if ln.strip()]
        errors = [ln for ln in lines if ln.startswith("error: ")]
        assert len(errors) == 1 and lines[-1] == errors[0], stderr
        assert "/" in errors[0], f"the error does not name a file: {errors[0]}"
    _record(fmt, "ok" if code == 0 else "exit 2")


@fuzz_settings(PLANNED["cli"])
@given(data=st.data(), target=st.sampled_from(["map", "map", "dataset"]))
def test_fuzz_cli_evaluate(map_base, seven_base, work, data, target):
    """`slamreloc evaluate MAP DATASET` on a damaged map or dataset."""
    case = Path(tempfile.mkdtemp(dir=work))
    map_dir, ds = case / "map", case / "ds"
    shutil.copytree(map_base, map_dir, copy_function=os.link)
    shutil.copytree(seven_base, ds, copy_function=os.link)
    root = map_dir if target == "map" else ds
    rel, change = data.draw(damaged_file(root, _files(root)) if target == "dataset" else
                            st.sampled_from([META, WEIGHTS, DATABASE]).flatmap(
                                lambda n: st.tuples(st.just(n), damaged_bytes(
                                    (map_dir / n).read_bytes()) if n != META else damaged_json(
                                    json.loads((map_dir / META).read_text())))))
    _apply(root, rel, change)
    method = data.draw(st.sampled_from(["regressor", "matching"]))
    code, stderr = _cli(["evaluate", str(map_dir), str(ds), "--split", "test", "--method", method,
                         "--report", str(case / "r.json")])
    check_cli_outcome(code, stderr, "cli")
    shutil.rmtree(case)


def test_fuzz_cli_ran():
    _assert_ran("cli")


@fuzz_settings(PLANNED["cli_colmap"])
@given(data=st.data(), base=st.sampled_from(sorted(COLMAP_BASES)))
def test_fuzz_cli_evaluate_colmap(map_base, colmap_bases, work, data, base):
    """`slamreloc evaluate MAP COLMAP_PROJECT` on a damaged COLMAP project."""
    case = Path(tempfile.mkdtemp(dir=work))
    map_dir, ds = case / "map", case / "project"
    shutil.copytree(map_base, map_dir, copy_function=os.link)
    shutil.copytree(colmap_bases[base], ds, copy_function=os.link)
    for rel, change in data.draw(damaged_colmap(colmap_bases[base])):
        if (ds / rel).is_file():
            _apply(ds, rel, change)
        elif change not in ("remove", "dir"):
            (ds / rel).write_bytes(change)
    code, stderr = _cli(["evaluate", str(map_dir), str(ds), "--split", "train", "--report",
                         str(case / "r.json")])
    check_cli_outcome(code, stderr, "cli_colmap")
    shutil.rmtree(case)


def test_fuzz_cli_colmap_ran():
    _assert_ran("cli_colmap")


# --- the budget: last in the module, after every fuzz test --------------------------------------

def test_fuzz_budget_ran(request):
    """At least BUDGET generated cases were executed by this module's fuzz tests (`_record`
    counts each case as it ends). Meaningful only when all of them were selected."""
    fuzz_tests = {name for name, fn in vars(request.module).items()
                  if getattr(fn, "is_hypothesis_test", False)}
    order = [item.originalname for item in request.session.items
             if item.module is request.module]
    if not fuzz_tests <= set(order):
        pytest.skip("the budget counts the whole module; some of its fuzz tests are deselected")
    assert max(order.index(name) for name in fuzz_tests) < order.index(request.node.originalname)
    ran = sum(n for (fmt, _), n in COUNTS.items() if fmt in PLANNED)
    assert ran >= math.ceil(BUDGET * min(SCALE, 1.0)), f"only {ran} fuzz cases ran"
