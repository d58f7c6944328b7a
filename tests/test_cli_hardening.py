"""The CLI attack round's findings (outputs, corrupt JPEGs, numbers, option ranges, signals,
map schema, dataset duplicates), each as its class: the command ends with one `error:` line
naming the file (and line) or the option, exit status 2, and nothing that is not its own output
changes. CLI cases run the real command line (`python -m slamreloc.cli`); the rules behind them
are also checked in process on generated inputs (hypothesis)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from slamreloc.errors import InputError
from slamreloc.io.outputs import check_outputs
from slamreloc.io.images import decode_rgb, read_image
from slamreloc.io.numbers import number_problem, parse_number
from slamreloc.map.format import META
from tests.test_fuzz_inputs import _tiny_map, make_sevenscenes

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared" / "data"
FAST = settings(max_examples=40, deadline=None, derandomize=True, database=None)


def cli(*argv, timeout: float = 120) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"}
    return subprocess.run([sys.executable, "-m", "slamreloc.cli", *map(str, argv)], cwd=REPO,
                          env=env, capture_output=True, text=True, timeout=timeout)


def one_error_line(res: subprocess.CompletedProcess, *words: str) -> str:
    """The single `error:` line of a failed command, holding every one of `words`."""
    assert res.returncode == 2 and "Traceback" not in res.stderr, res.stderr
    (line,) = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert line.startswith("error: "), line
    for w in words:
        assert w in line, (w, line)
    return line


@pytest.fixture(scope="module")
def tiny_map(tmp_path_factory) -> Path:
    return _tiny_map(tmp_path_factory.mktemp("hardening") / "map")


@pytest.fixture(scope="module")
def jpeg() -> bytes:
    rng = np.random.default_rng(0)
    img = cv2.resize(rng.integers(0, 255, (30, 40, 3), np.uint8), (320, 240),
                     interpolation=cv2.INTER_CUBIC)
    return cv2.imencode(".jpg", img)[1].tobytes()


# --- #1 #2 #3 #18: outputs ---------------------------------------------------------------

def test_an_output_that_is_a_link_to_a_stream_is_refused_and_kept(tiny_map, tmp_path):
    link = tmp_path / "out.tum"
    link.symlink_to("/proc/self/fd/1")  # as /dev/stdout is
    one_error_line(cli("export", tiny_map, "--tum", link), "--tum", "symbolic link")
    assert link.is_symlink() and os.readlink(link) == "/proc/self/fd/1"
    with pytest.raises(InputError, match="--report"):
        check_outputs({"--report": "/dev/stdout"}, {})
    with pytest.raises(InputError, match="--report"):
        check_outputs({"--report": "/proc/self/fd/1"}, {})


def test_outputs_of_one_command_never_overlap(tiny_map, tmp_path):
    one_error_line(cli("export", tiny_map, "--colmap", tmp_path / "cm", "--ply",
                       tmp_path / "cm" / "cameras.txt"), "--ply", "--colmap", "inside")
    assert not (tmp_path / "cm").exists()
    with pytest.raises(InputError, match="inside"):
        check_outputs({"--out": tmp_path / "m", "--report": tmp_path / "m" / "r.json"}, {},
                      folders=("--out",))


def test_a_foreign_file_where_a_names_sidecar_goes_is_kept(tiny_map, tmp_path):
    mine = tmp_path / "mine.names.txt"
    mine.write_text("notes\n")
    one_error_line(cli("export", tiny_map, "--tum", tmp_path / "mine.tum"),
                   "names file", "mine.names.txt")
    assert mine.read_text() == "notes\n" and not (tmp_path / "mine.tum").exists()
    # its own sidecar, from an earlier export, is replaced
    res = cli("export", tiny_map, "--tum", tmp_path / "own.tum")
    assert res.returncode == 0, res.stderr
    res = cli("export", tiny_map, "--tum", tmp_path / "own.tum")
    assert res.returncode == 0, res.stderr


@pytest.mark.parametrize("path", ["/proc/x.ply", "/sys/x.ply"])
def test_an_output_where_nothing_can_be_written_is_refused_before_the_work(tiny_map, path):
    one_error_line(cli("export", tiny_map, "--ply", path), path, "--ply", "cannot be written")


# --- #4 #5 #6: JPEG -------------------------------------------------------------------------

def _cut_with_eoi(data: bytes, share: float) -> bytes:
    sos = data.index(b"\xff\xda")
    start = sos + 2 + int.from_bytes(data[sos + 2:sos + 4], "big")
    return data[:start + int(share * (len(data) - 2 - start))] + b"\xff\xd9"


@FAST
@given(share=st.floats(0.0, 0.97))
def test_a_jpeg_cut_in_its_scan_with_an_end_marker_is_refused(jpeg, share):
    with pytest.raises(InputError, match="cut.jpg: not a readable image"):
        decode_rgb(_cut_with_eoi(jpeg, share), "cut.jpg")


@FAST
@given(seed=st.integers(0, 10_000))
def test_bit_flips_in_a_jpeg_never_pass_as_silently_corrupt(jpeg, seed):
    """A flipped JPEG is refused or decodes without libjpeg finding it corrupt: never a
    warning on stderr and a picture padded with grey."""
    rng = np.random.default_rng(seed)
    data = bytearray(jpeg)
    for _ in range(20):
        data[int(rng.integers(2, len(data) - 2))] ^= 1 << int(rng.integers(0, 8))
    try:
        decode_rgb(bytes(data), "flipped.jpg")
    except InputError as err:
        assert "flipped.jpg" in str(err)


def test_trailing_bytes_after_the_end_marker_are_not_the_image(jpeg):
    extra = np.random.default_rng(1).bytes(1000)
    assert decode_rgb(jpeg + extra, "t.jpg").shape == (240, 320, 3)
    png = cv2.imencode(".png", np.zeros((64, 64, 3), np.uint8))[1].tobytes()
    assert decode_rgb(png + extra, "t.png").shape == (64, 64, 3)


def test_exif_orientation_is_not_applied(jpeg, tmp_path):
    from PIL import Image

    im = Image.fromarray(cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR))
    exif = im.getexif()
    exif[0x0112] = 6  # rotate 90 degrees: a portrait phone photo
    im.save(tmp_path / "r.jpg", exif=exif)
    assert read_image(tmp_path / "r.jpg").shape == (240, 320, 3)


def test_a_corrupt_jpeg_is_one_error_line_in_localize(tiny_map, jpeg, tmp_path):
    bad = tmp_path / "t.jpg"
    bad.write_bytes(_cut_with_eoi(jpeg, 0.5))
    res = cli("localize", tiny_map, bad)
    one_error_line(res, "t.jpg", "JPEG")
    assert "Corrupt JPEG data" not in res.stderr


@pytest.mark.skipif(not SHARED.is_dir(), reason=f"real data not found at {SHARED}")
def test_every_real_jpeg_is_still_read():
    jpegs = [p for p in SHARED.rglob("*") if p.suffix.lower() in (".jpg", ".jpeg")]
    for path in jpegs:
        read_image(path)


# --- #7: numbers ----------------------------------------------------------------------------

@FAST
@given(x=st.floats(allow_nan=False, allow_infinity=False))
def test_every_float_python_writes_is_a_number(x):
    assert number_problem(repr(x)) is None and parse_number(repr(x), "f") == x


@pytest.mark.parametrize("text", ["1_0", "\u0663", "nan", "inf", "-Infinity", "0x1p3", " 1",
                                  "1e999", "", "1.2.3", "\uff11"])
def test_what_python_reads_as_a_number_but_no_file_means_is_not(text):
    assert number_problem(text) is not None


def test_text_files_name_the_file_and_line_of_a_bad_number(tmp_path):
    from slamreloc.datasets.colmap_check import _read_images_text
    from slamreloc.datasets.io import read_intrinsics

    k = tmp_path / "intrinsics.txt"
    k.write_text("525 0 320\n0 5_25 240\n0 0 1\n")
    with pytest.raises(InputError, match=r"intrinsics.txt:2: .*'5_25' is not a number"):
        read_intrinsics(k)
    images = tmp_path / "images.txt"
    images.write_text("1 1 0 0 0 0 0 0 1 a.png\nnan nan -1\n")
    with pytest.raises(InputError, match=r"images.txt:2: "):
        _read_images_text(images)
    images.write_text("1 1 0 0 0 0 0 \u0663 1 a.png\n\n")
    with pytest.raises(InputError, match=r"images.txt:1: "):
        _read_images_text(images)


def test_a_limit_is_an_ascii_number(tiny_map):
    one_error_line(cli("--limit", "max_image_pixels=1_000", "export", tiny_map, "--tum", "x"),
                   "max_image_pixels")


# --- #8 #10 #12 #11 #22: options ------------------------------------------------------------

@pytest.mark.parametrize("argv, words", [
    (["map", "DS", "--out", "OUT", "--epochs", "99999999999999999999"], ["--epochs", "1..100000"]),
    (["map", "DS", "--out", "OUT", "--epochs", "0"], ["--epochs"]),
    (["pseudo-label", "MAP", "DS", "--out", "OUT", "--report", "R", "--rounds", "10000000"],
     ["--rounds"]),
    (["sfm", "PHOTOS", "--out", "OUT", "--max-features", "99999999999999"],
     ["--max-features"]),
    (["sfm", "PHOTOS", "--out", "OUT", "--fix-intrinsics"], ["--fix-intrinsics", "--camera"]),
    (["sfm", "PHOTOS", "--out", "OUT", "--split", "train"], ["--split"]),
    (["localize", "MAP", "X.png", "--intrinsics", "262.5", "262.5", "160"], ["--intrinsics"]),
    (["map", "DS", "--out", "OUT", "--epochs", "x"], ["--epochs"]),
    (["export", "MAP", "--bogus"], ["--bogus"]),
])
def test_option_errors_are_one_line(tmp_path, tiny_map, argv, words):
    photos = tmp_path / "PHOTOS"
    photos.mkdir()
    for i in range(2):
        cv2.imwrite(str(photos / f"{i}.png"), np.full((48, 64, 3), 40 * i, np.uint8))
    names = {"MAP": tiny_map, "PHOTOS": photos}
    argv = [names.get(a, tmp_path / a if a.isupper() else a) for a in argv]
    one_error_line(cli(*argv), *words)
    assert not (tmp_path / "OUT").exists()


def test_a_photo_of_another_size_in_an_sfm_folder_is_refused(tmp_path):
    photos = tmp_path / "photos"
    photos.mkdir()
    rng = np.random.default_rng(0)
    for i, size in enumerate([(64, 48), (64, 48), (128, 96)]):
        cv2.imwrite(str(photos / f"{i}.png"), rng.integers(0, 255, (size[1], size[0], 3),
                                                          np.uint8))
    one_error_line(cli("sfm", photos, "--out", tmp_path / "out"), "2.png", "128x96", "64x48")
    assert not (tmp_path / "out").exists()


def test_help_is_still_shown():
    res = cli("--help")
    assert res.returncode == 0 and "Usage" in res.stdout


# --- #9: SIGTERM ----------------------------------------------------------------------------

def test_sigterm_ends_quietly_even_after_pycolmap_is_imported():
    code = ("import os, signal, time\n"
            "from slamreloc.cli import sigterm_as_ctrl_c\n"
            "with sigterm_as_ctrl_c():\n"
            "    import pycolmap\n"
            "    try:\n"
            "        os.kill(os.getpid(), signal.SIGTERM); time.sleep(10)\n"
            "    except KeyboardInterrupt:\n"
            "        print('interrupted')\n")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=60, cwd=REPO)
    assert res.stdout.strip() == "interrupted" and "Aborted" not in res.stderr, res.stderr


# --- #13 #16 #17: the map's files -----------------------------------------------------------

@pytest.mark.parametrize("path, value, words", [
    (("labels", "median_reproj_error_px"), -1.0, ["median_reproj_error_px"]),
    (("train",), {"precision": "fp8"}, ["train.precision"]),
    (("regressor", "arch"), "bogus", ["regressor.arch"]),
])
def test_map_metadata_values_out_of_the_schema_are_refused(tiny_map, path, value, words):
    from slamreloc.map.meta import MapMeta

    doc = json.loads((tiny_map / META).read_text())
    obj = doc
    for key in path[:-1]:
        obj = obj[key]
    obj[path[-1]] = value
    with pytest.raises(InputError) as err:
        MapMeta.from_json(doc, "m.json")
    for w in words:
        assert w in str(err.value)


@pytest.mark.parametrize("key", ["in_std", "out_scale"])
def test_regressor_scales_must_be_positive(key):
    import torch

    from slamreloc.map.weights import _build_regressor
    from slamreloc.regressor.model import RegressorConfig, SceneCoordinateRegressor

    cfg = RegressorConfig(in_dim=8, hidden=(4,))
    state = dict(SceneCoordinateRegressor(cfg).state_dict())
    state[key] = torch.zeros_like(state[key])
    with pytest.raises(InputError, match=key):
        _build_regressor(cfg, state, Path("regressor.npz"))


# --- #14 #20 #23: datasets and pose files ---------------------------------------------------

def test_a_frame_with_two_colour_images_is_refused(tmp_path):
    from slamreloc.datasets import load_dataset

    root = make_sevenscenes(tmp_path / "ds")
    png = root / "seq-01" / "frame-000000.color.png"
    cv2.imwrite(str(png.with_suffix(".jpg")), cv2.imread(str(png)))
    with pytest.raises(InputError, match="frame-000000.*two colour images"):
        load_dataset(root)


def test_a_pose_file_that_is_a_pipe_or_a_device_says_so(tmp_path):
    from slamreloc.datasets.poses import read_poses

    fifo = tmp_path / "p.txt"
    os.mkfifo(fifo)
    with pytest.raises(InputError, match="named pipe"):
        read_poses(fifo)
    with pytest.raises(InputError, match="device"):
        read_poses(Path("/dev/zero"))


def test_a_repeated_frame_in_a_long_pose_file_fails_at_its_line(tmp_path):
    from slamreloc.datasets.poses import read_poses

    line = "seq-01/f 0 0 0 0 0 0 1\n"
    path = tmp_path / "p.txt"
    path.write_text("seq-01/a 0 0 0 0 0 0 1\n" + line * 200_000)
    with pytest.raises(InputError, match=r"p.txt:3: frame 'seq-01/f' .*line 2"):
        read_poses(path)


def test_a_query_without_ground_truth_names_the_dataset_not_a_file(tiny_map, tmp_path):
    root = make_sevenscenes(tmp_path / "ds")
    (root / "seq-02" / "frame-000001.pose.txt").unlink()
    one_error_line(cli("evaluate", tiny_map, root, "--report", tmp_path / "r.json"),
                   str(root), "seq-02/frame-000001", "no ground-truth pose", "--poses")
    assert not (tmp_path / "r.json").exists()
