"""Poses from elsewhere (`--poses FILE`) and scoring against other references (`evaluate
--reference FILE`): the three pose formats, how frames are matched, the similarity fitted on
training cameras only, the REPORT.json keys, and the one-line errors.

The pose files are made by the project's own code: `slamreloc export --colmap --tum` writes the
map's training cameras as a COLMAP model and a TUM file with names; the named files are the
dataset's own poses moved by a known similarity (`Sim3.apply_to_pose`, `tum_line`).
"""

from __future__ import annotations

import json
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from slamreloc.datasets import apply_poses, load_dataset, read_poses
from slamreloc.errors import InputError
from slamreloc.localize.evaluate import IDENTITY_RESIDUAL, reference_alignment
from slamreloc.geometry import Rigid3, Sim3, axis_angle_to_matrix, pose_error, tum_line
from slamreloc.map.format import META
from tests.fuzzing import run_cli_output

# a rigid motion (a map trained on moved poses stays metric) and a similarity with a scale
MOVE = Sim3(1.0, axis_angle_to_matrix([0.3, -0.2, 1.1]), np.array([2.0, -1.0, 0.5]))
SCALED = Sim3(1.7, axis_angle_to_matrix([-0.4, 0.9, 0.2]), np.array([-3.0, 0.25, 1.5]))
N_LEFT_OUT = 5  # queries the partial reference has no pose for


def moved(world_from_cam: dict[str, Rigid3], sim: Sim3) -> dict[str, Rigid3]:
    return {name: sim.apply_to_pose(p) for name, p in world_from_cam.items()}


def write_named(path: Path, world_from_cam: dict[str, Rigid3]) -> Path:
    path.write_text("# name tx ty tz qx qy qz qw (world_from_cam)\n"
                    + "".join(tum_line(n, p) + "\n" for n, p in world_from_cam.items()))
    return path


def sim3_matrix(sim: Sim3) -> np.ndarray:
    return np.column_stack([sim.scale * sim.rotation, sim.translation])


def cli(*args, hang_s: float = 600.0) -> tuple[int, str, str]:
    return run_cli_output([str(a) for a in args], hang_s)


@contextmanager
def wide_console(width: int = 200):
    """The CLI's tables at a terminal's width, whatever runs the tests."""
    from slamreloc.runtime.progress import console

    saved = console._width  # rich has no public way back to "the terminal's width"
    console.width = width
    try:
        yield
    finally:
        console._width = saved


def one_error_line(code: int, err: str, names: str) -> str:
    """The run ended in exit 2 with one `error: <names>...` line, no traceback."""
    assert code == 2, err
    assert "Traceback" not in err, err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith(f"error: {names}"), lines
    return lines[0]


@pytest.fixture(scope="module")
def truth(scene_dir) -> dict[str, Rigid3]:
    """The scene's own world_from_cam of every frame, by name."""
    return {f.name: f.world_from_cam for f in load_dataset(scene_dir).frames("all")}


@pytest.fixture(scope="module")
def files(scene_dir, small_map, truth, tmp_path_factory) -> dict[str, Path]:
    """Pose files of the scene: the export of the map's training cameras (COLMAP + TUM), the
    truth as a named file, moved and scaled copies, and a copy that lacks some queries."""
    work = tmp_path_factory.mktemp("poses")
    code, _, err = cli("export", small_map.root, "--colmap", work / "colmap", "--tum",
                       work / "train.txt")
    assert code == 0, err
    queries = [f.name for f in load_dataset(scene_dir).frames("test")]
    partial = {n: p for n, p in truth.items() if n not in queries[:N_LEFT_OUT]}
    return {"colmap": work / "colmap", "tum": work / "train.txt",
            "same": write_named(work / "same.txt", truth),
            "moved": write_named(work / "moved.txt", moved(truth, MOVE)),
            "scaled": write_named(work / "scaled.txt", moved(truth, SCALED)),
            "partial": write_named(work / "partial.txt", partial), "work": work}


def assert_same_poses(got: dict[str, Rigid3], want: dict[str, Rigid3], tol_m: float = 1e-5):
    assert set(got) == set(want)
    for name, pose in want.items():
        dt, dr = pose_error(got[name], pose)
        assert dt < tol_m and dr < 1e-3, (name, dt, dr)


# --- reading the three formats ----------------------------------------------------------------

def test_reads_a_named_file(files, truth):
    ref = read_poses(files["moved"])
    assert ref.kind == "named" and ref.source == files["moved"].resolve()
    assert len(ref.stamps) == 0
    assert_same_poses(ref.world_from_cam, moved(truth, MOVE))


def test_reads_the_tum_file_and_its_names_that_export_writes(files, small_map):
    ref = read_poses(files["tum"])
    assert ref.kind == "tum" and len(ref.stamps) == 0  # every stamp named by the sidecar
    db = small_map.database
    want = {n: Rigid3.from_matrix(m, tol=1e-2) for n, m in zip(db.frame_names,
                                                                db.world_from_cam)}
    assert_same_poses(ref.world_from_cam, want)


@pytest.mark.parametrize("layout", ["model", "project"])
def test_reads_a_colmap_model_folder_or_project(files, small_map, tmp_path, layout):
    """The folder holding cameras/images, or a folder with sparse/0 holding them; names are
    the images' paths (the frames' image files relative to the dataset root)."""
    folder = files["colmap"]
    if layout == "project":
        (tmp_path / "sparse").mkdir()
        (tmp_path / "sparse" / "0").symlink_to(folder, target_is_directory=True)
        folder = tmp_path
    ref = read_poses(folder)
    assert ref.kind == "colmap"
    db = small_map.database
    want = {f"{n}.color.png": Rigid3.from_matrix(m, tol=1e-2)
            for n, m in zip(db.frame_names, db.world_from_cam)}
    assert_same_poses(ref.world_from_cam, want)


# --- matching frames ------------------------------------------------------------------------

def test_apply_poses_by_name_and_by_image_path(scene_dir, files, truth):
    dataset = load_dataset(scene_dir)
    by_name = apply_poses(dataset, read_poses(files["moved"]))
    assert by_name.poses_source == str(files["moved"].resolve())
    assert by_name.poses_matched == len(truth)
    assert_same_poses({f.name: f.world_from_cam for f in by_name.frames("all")},
                      moved(truth, MOVE))
    # the COLMAP export names the training images by path: only those frames get a pose
    by_path = apply_poses(dataset, read_poses(files["colmap"]))
    train = {f.name for f in dataset.frames("train")}
    assert by_path.poses_matched == len(train)
    for f in by_path.frames("all"):
        assert (f.world_from_cam is not None) == (f.name in train), f.name
    assert dataset.poses_source == "dataset"  # the dataset given is left as it was


def test_apply_poses_by_name_with_image_suffixes_stripped(scene_dir, truth, tmp_path):
    path = write_named(tmp_path / "jpg.txt", {f"{n}.color.jpg": p for n, p in
                                              moved(truth, MOVE).items()})
    applied = apply_poses(load_dataset(scene_dir), read_poses(path))
    assert applied.poses_matched == len(truth)
    assert_same_poses({f.name: f.world_from_cam for f in applied.frames("all")},
                      moved(truth, MOVE))


def test_apply_poses_by_timestamp_within_20ms(scene_dir, tmp_path):
    """A TUM file without names: each frame takes the pose nearest in time, within 20 ms;
    rows of a frame 30 ms off match nothing."""
    dataset = load_dataset(scene_dir)
    frames = dataset.frames("seq-02")
    one = replace(dataset, sequences={"seq-02": frames}, splits={}, roles={})
    off = {3: 0.005, 4: -0.015, 7: 0.030}  # seconds
    path = tmp_path / "stamps.txt"
    path.write_text("".join(tum_line(f"{f.timestamp + off.get(i, 0.0):.6f}",
                                     MOVE.apply_to_pose(f.world_from_cam)) + "\n"
                            for i, f in enumerate(frames)))
    ref = read_poses(path)
    assert ref.kind == "tum" and not ref.world_from_cam and len(ref.stamps) == len(frames)
    applied = apply_poses(one, ref)
    assert applied.poses_matched == len(frames) - 1
    for i, (f, g) in enumerate(zip(frames, applied.frames("all"))):
        if i == 7:
            assert g.world_from_cam is None
        else:
            dt, dr = pose_error(g.world_from_cam, MOVE.apply_to_pose(f.world_from_cam))
            assert dt < 1e-5 and dr < 1e-3
    # the scene's sequences share their timestamps: unnamed rows cannot tell them apart
    with pytest.raises(InputError, match="without frame names") as err:
        apply_poses(dataset, ref)
    assert str(err.value).startswith(str(path.resolve()))


def test_a_file_naming_no_frame_is_an_error(scene_dir, tmp_path):
    path = write_named(tmp_path / "other.txt", {"kitchen/0001.png": Rigid3.identity(),
                                                "kitchen/0002.png": Rigid3.identity()})
    with pytest.raises(InputError) as err:
        apply_poses(load_dataset(scene_dir), read_poses(path))
    msg = str(err.value)
    assert msg.startswith(f"{path.resolve()}: names no frame of")
    assert "2 poses" in msg and "'kitchen/0001.png'" in msg and "'seq-01/frame-000000'" in msg


# --- the alignment maths ----------------------------------------------------------------------

vec3 = st.lists(st.floats(-3.0, 3.0, allow_nan=False), min_size=3, max_size=3).map(np.array)


@settings(max_examples=60, deadline=None, derandomize=True, database=None)
@given(rotvec=vec3, translation=vec3.map(lambda v: 3 * v), log_scale=st.floats(-2.0, 2.0),
       seed=st.integers(0, 2**31 - 1), n=st.integers(3, 15))
def test_alignment_recovers_a_random_similarity(rotvec, translation, log_scale, seed, n):
    """Cameras moved by a random similarity: the fit on them recovers it exactly (residual
    ~0), or applies none where it moves the cameras by less than the identity tolerance."""
    rng = np.random.default_rng(seed)
    ref_from_map = Sim3(float(np.exp(log_scale)), axis_angle_to_matrix(rotvec), translation)
    map_from_cam = {f"f{i}": Rigid3(axis_angle_to_matrix(rng.uniform(-3, 3, 3)),
                                    rng.uniform(-5, 5, 3)) for i in range(n)}
    reference = moved(map_from_cam, ref_from_map)
    fitted, record = reference_alignment(map_from_cam, reference, "ref.txt")
    assert record["n_frames"] == n
    shift = [pose_error(map_from_cam[k], reference[k]) for k in map_from_cam]
    if record["aligned"]:
        np.testing.assert_allclose(record["scale"], ref_from_map.scale, rtol=1e-6)
        np.testing.assert_allclose(np.array(record["matrix"]), sim3_matrix(ref_from_map),
                                   atol=1e-6 * (1 + np.abs(translation).max()))
        assert record["median_residual_m"] < 1e-6 and record["median_residual_deg"] < 1e-4
        assert fitted is not None
    else:
        assert fitted is None and record["scale"] == 1.0
        assert np.median([s[0] for s in shift]) < IDENTITY_RESIDUAL[0]
        assert np.median([s[1] for s in shift]) < IDENTITY_RESIDUAL[1]


@pytest.mark.parametrize("offset_m, aligned", [(0.0, False), (0.0005, False), (0.002, True)])
def test_a_reference_in_the_map_frame_needs_no_transform(offset_m, aligned):
    map_from_cam = {f"f{i}": Rigid3(axis_angle_to_matrix([0.1 * i, 0, 0.2]),
                                    np.array([i, i % 2, 0.5 * i])) for i in range(6)}
    shift = Sim3(1.0, np.eye(3), np.array([offset_m, 0.0, 0.0]))
    fitted, record = reference_alignment(map_from_cam, moved(map_from_cam, shift))
    assert record["aligned"] is aligned and (fitted is None) is (not aligned)
    assert record["median_residual_m"] < (1e-9 if aligned else IDENTITY_RESIDUAL[0])


def test_fewer_than_three_shared_frames_is_an_error():
    poses = {f"f{i}": Rigid3(np.eye(3), np.array([i, 0.0, 0.0])) for i in range(2)}
    with pytest.raises(InputError, match="^ref.txt: only 2 training frames"):
        reference_alignment(poses, poses, "ref.txt")


# --- evaluate --reference on the shared map -------------------------------------------------

@pytest.fixture(scope="module")
def evaluated(small_map, scene_dir, files, tmp_path_factory):
    """One `evaluate` of the map (trained on the scene's own poses) against the dataset and
    three references: a scaled copy, the same poses as a file, one lacking some queries."""
    out = tmp_path_factory.mktemp("evaluated")
    with wide_console():
        code, _, err = cli("evaluate", small_map.root, scene_dir, "--report", out / "r.json",
                           "--trajectory", out / "t.txt", "--reference", files["scaled"],
                           "--reference", files["same"], "--reference", files["partial"])
    assert code == 0, err
    return json.loads((out / "r.json").read_text()), err, out


def test_report_keeps_the_contract_and_says_which_reference(evaluated):
    report, _, out = evaluated
    for key in ("method", "n_queries", "n_localized", "median_translation_m",
                "median_rotation_deg", "recall", "timing_ms", "map", "device"):
        assert key in report
    assert set(report["recall"]) == {"1cm1deg", "2cm2deg", "5cm5deg", "10cm5deg"}
    assert report["reference"] == "dataset" and report["dataset"]["poses"] == "dataset"
    assert (out / "t.txt").is_file() and (out / "t.names.txt").is_file()  # --trajectory
    for entry in report["references"].values():
        assert set(entry) >= {"file", "alignment", "n_queries", "n_localized",
                              "median_translation_m", "median_rotation_deg", "recall"}
        assert set(entry["alignment"]) >= {"scale", "n_frames", "median_residual_m",
                                           "median_residual_deg", "matrix", "aligned"}
        assert set(entry["recall"]) == set(report["recall"])


def test_a_scaled_reference_is_aligned_on_training_cameras(evaluated, files, small_map):
    report, _, _ = evaluated
    ref = report["references"]["scaled.txt"]
    assert ref["file"] == str(files["scaled"].resolve())
    a = ref["alignment"]
    assert a["aligned"] is True and a["n_frames"] == len(small_map.database.frame_names)
    assert a["scale"] == pytest.approx(SCALED.scale, rel=1e-5)
    np.testing.assert_allclose(np.array(a["matrix"]), sim3_matrix(SCALED), atol=1e-4)
    assert a["median_residual_m"] < 1e-5 and a["median_residual_deg"] < 1e-3
    # the same estimates, in a frame 1.7 times larger: translation errors scale, angles stay
    assert ref["n_queries"] == report["n_queries"] and ref["n_localized"] == report["n_localized"]
    assert ref["median_translation_m"] == pytest.approx(
        SCALED.scale * report["median_translation_m"], rel=1e-3, abs=1e-5)
    assert ref["median_rotation_deg"] == pytest.approx(report["median_rotation_deg"], abs=1e-3)


def test_the_same_poses_as_a_file_need_no_transform(evaluated, files):
    report, _, _ = evaluated
    ref = report["references"]["same.txt"]
    assert ref["alignment"]["aligned"] is False and ref["alignment"]["scale"] == 1.0
    assert ref["alignment"]["matrix"] == np.eye(4)[:3].tolist()
    assert ref["recall"] == report["recall"]
    assert ref["median_translation_m"] == pytest.approx(report["median_translation_m"],
                                                        abs=1e-5)


def test_queries_the_reference_lacks_are_counted_and_left_out(evaluated, files):
    report, printed, _ = evaluated
    ref = report["references"]["partial.txt"]
    assert ref["n_queries"] == report["n_queries"] - N_LEFT_OUT
    assert ref["n_queries_without_reference"] == N_LEFT_OUT
    assert ("reference partial.txt: in the map's frame already (no transform)"
            in " ".join(printed.split()))
    assert f"{N_LEFT_OUT} queries it has no pose for are left out" in " ".join(printed.split())


def test_the_table_has_a_row_per_reference(evaluated):
    _, printed, _ = evaluated
    header = next(ln for ln in printed.splitlines() if "1cm1deg" in ln)
    for col in ("reference", "2cm2deg", "5cm5deg", "10cm5deg"):
        assert col in header
    rows = [ln for ln in printed.splitlines() if " %" in ln]
    assert len(rows) == 4 and "dataset" in rows[0]
    for row, name in zip(rows[1:], ("scaled.txt", "same.txt", "partial.txt")):
        assert name in row


# --- map --poses: a map in another frame, scored against the original poses ----------------

def test_map_trained_on_moved_poses_scores_the_same_against_the_original(scene_dir, files,
                                                                          truth, tmp_path,
                                                                          small_map):
    """`map --poses` of a rigidly moved copy: the map records the file and lives in the moved
    frame; `evaluate --poses` of that copy scores in the map's frame, and `--reference` of the
    original poses recovers the motion's inverse from the training cameras, with the same
    recalls."""
    map_dir = tmp_path / "moved_map"
    with wide_console(400):
        code, _, err = cli("map", scene_dir, "--out", map_dir, "--poses", files["moved"],
                           "--arch", "tiny", "--epochs", "2")
    assert code == 0, err
    assert f"poses: from {files['moved'].resolve()} (--poses)" in " ".join(err.split())
    meta = json.loads((map_dir / META).read_text())
    assert meta["dataset"]["poses"] == str(files["moved"].resolve())
    # the scene's depth labels keypoints with its own poses, never with poses from elsewhere
    assert meta["labels"]["n_depth_labels"] == 0 and meta["labels"]["n_labelled"] > 0
    own = json.loads((Path(small_map.root) / META).read_text())["labels"]
    assert own["n_depth_labels"] > 0
    code, _, err = cli("evaluate", map_dir, scene_dir, "--method", "matching",
                            "--report", tmp_path / "r.json", "--poses", files["moved"],
                            "--reference", files["same"], "--reference", scene_dir)
    assert code == 0, err
    report = json.loads((tmp_path / "r.json").read_text())
    assert report["reference"] == report["dataset"]["poses"] == str(files["moved"].resolve())
    assert report["n_localized"] > report["n_queries"] // 2
    ref = report["references"]["same.txt"]
    a = ref["alignment"]
    assert a["aligned"] is True and a["scale"] == pytest.approx(1.0, abs=1e-5)
    inverse = Rigid3(MOVE.rotation, MOVE.translation).inverse()
    np.testing.assert_allclose(np.array(a["matrix"]), inverse.matrix3x4(), atol=1e-4)
    assert a["median_residual_m"] < 1e-5 and a["median_residual_deg"] < 1e-3
    assert ref["recall"] == report["recall"]
    assert ref["median_translation_m"] == pytest.approx(report["median_translation_m"],
                                                        abs=1e-5)
    assert ref["median_rotation_deg"] == pytest.approx(report["median_rotation_deg"], abs=1e-3)
    # the dataset folder itself as a reference: its own poses, the same as the file of them
    own_poses = report["references"][Path(scene_dir).name]
    assert own_poses["recall"] == ref["recall"]
    # (the file holds the poses to 6 decimals, the dataset to full precision)
    np.testing.assert_allclose(own_poses["alignment"]["matrix"], a["matrix"], atol=1e-5)


def test_view_shows_the_poses_file_as_ground_truth(small_map, scene_dir, files, truth):
    from slamreloc.viewer import ViewerInputs, load_scene_data

    data = load_scene_data(ViewerInputs(small_map.root, [files["tum"]], [], scene_dir,
                                        poses=files["moved"]))
    traj = next(t for t in data.trajectories if t.path == files["tum"])
    want = moved(truth, MOVE)
    assert len(traj) == len(traj.truth) > 0
    for name, got in zip(traj.names, traj.truth):
        dt, dr = pose_error(got, want[name])
        assert dt < 1e-5 and dr < 1e-3


# --- errors through the command line ----------------------------------------------------------

def test_missing_pose_file_is_one_line_for_every_command(small_map, scene_dir, tmp_path):
    missing = tmp_path / "missing.txt"
    runs = {
        "map": ["map", scene_dir, "--out", tmp_path / "m", "--poses", missing],
        "evaluate": ["evaluate", small_map.root, scene_dir, "--report", tmp_path / "r.json",
                     "--poses", missing],
        "evaluate --reference": ["evaluate", small_map.root, scene_dir, "--report",
                                 tmp_path / "r.json", "--reference", missing],
        "slam": ["slam", scene_dir, "--map", small_map.root, "--report", tmp_path / "r.json",
                 "--poses", missing],
        "pseudo-label": ["pseudo-label", small_map.root, scene_dir, "--out", tmp_path / "n",
                         "--report", tmp_path / "r.json", "--poses", missing],
        "view": ["view", small_map.root, "--dataset", scene_dir, "--poses", missing],
    }
    for command, argv in runs.items():
        code, _, err = cli(*argv, hang_s=120)
        line = one_error_line(code, err, str(missing))
        assert line.endswith("pose file not found"), (command, line)
        assert not (tmp_path / "r.json").exists() and not (tmp_path / "m").exists(), command
        assert not (tmp_path / "n").exists(), command


def test_malformed_line_names_the_file_and_line(small_map, scene_dir, truth, tmp_path):
    bad = write_named(tmp_path / "bad.txt", dict(list(truth.items())[:3]))
    bad.write_text(bad.read_text() + "seq-01/frame-000003 1 2 3 0 0 0\n")
    code, _, err = cli("evaluate", small_map.root, scene_dir, "--report", tmp_path / "r.json",
                       "--poses", bad)
    line = one_error_line(code, err, f"{bad}:5: ")
    assert "expected 8 fields" in line
    assert not (tmp_path / "r.json").exists()


def test_a_file_naming_no_frame_writes_no_map(scene_dir, tmp_path):
    other = write_named(tmp_path / "other.txt", {"kitchen/0001.png": Rigid3.identity()})
    code, _, err = cli("map", scene_dir, "--out", tmp_path / "m", "--poses", other)
    line = one_error_line(code, err, f"{other.resolve()}: names no frame")
    assert "(1 pose, the first 'kitchen/0001.png'" in line
    assert not (tmp_path / "m").exists()


def test_a_reference_with_fewer_than_three_training_frames(small_map, scene_dir, truth,
                                                           tmp_path):
    """Two training frames (and every query) are not enough to align; nor is a reference
    whose training frames are all queries of the evaluation (the fit never uses queries)."""
    train = list(small_map.database.frame_names)
    queries = [f.name for f in load_dataset(scene_dir).frames("test")]
    two = write_named(tmp_path / "two.txt", {n: truth[n] for n in [*train[:2], *queries]})
    for path, split, n in ((two, "test", 2), (write_named(tmp_path / "all.txt", truth),
                                               "train", 0)):
        code, _, err = cli("evaluate", small_map.root, scene_dir, "--split", split,
                           "--report", tmp_path / "r.json", "--reference", path)
        line = one_error_line(code, err, f"{path.resolve()}: only {n} training frames")
        assert "at least 3" in line
        assert not (tmp_path / "r.json").exists()


def test_a_reference_without_queries_is_an_error(small_map, scene_dir, files, tmp_path):
    """The export of the map's training cameras has no query to score."""
    code, _, err = cli("evaluate", small_map.root, scene_dir, "--report", tmp_path / "r.json",
                       "--reference", files["colmap"])
    line = one_error_line(code, err, f"{files['colmap'].resolve()}: has a pose for none of "
                                     "the 20 queries")
    assert "60 of the map's training frames" in line
    assert not (tmp_path / "r.json").exists()


def test_pseudo_label_scores_against_the_poses_file(scene_dir, files, truth):
    """`pseudo-label --poses`: the truth of the report from the file, matched to --truth's
    frames if given, else to the dataset's (whose own poses are then not the truth)."""
    from slamreloc.cli.jobs import scoring_truth
    from slamreloc.pseudo_label.update import _truth_poses

    dataset = load_dataset(scene_dir)
    frames = dataset.frames("unlabelled")
    want = [MOVE.apply_to_pose(truth[f.name]) for f in frames]
    for truth_dir in (None, scene_dir):
        reference = scoring_truth(dataset, truth_dir, files["moved"])
        poses, source = _truth_poses(dataset, frames, reference)
        assert source == str(files["moved"].resolve())
        for got, pose in zip(poses, want):
            dt, dr = pose_error(got, pose)
            assert dt < 1e-5 and dr < 1e-3
    poses, source = _truth_poses(dataset, frames, scoring_truth(dataset, scene_dir, None))
    assert source == str(scene_dir.resolve()) and poses[0] is not None
    assert scoring_truth(dataset, None, None) is None
    assert _truth_poses(dataset, frames, None)[1] == "dataset"
