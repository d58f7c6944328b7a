"""Attack round 23 B, COLMAP models as input: a text model's memory is a small multiple of its
size (B1), text models and split files take the `max_text_bytes` bound (B2), COLMAP >= 3.12
rigs and frames are checked like the other model files and name the file that holds a bad
value (B3, B4), an image that is a pipe or a device is said to be one (B5), and image names
in images.txt have images.bin's bound (B6)."""

from __future__ import annotations

import os
import struct
import tracemalloc
from pathlib import Path

import pytest

from slamreloc.datasets import load_dataset
from slamreloc.datasets.colmap import read_checked
from slamreloc.datasets.colmap_check import MAX_NAME_BYTES, check_model
from slamreloc.errors import InputError
from slamreloc.geometry import QUATERNION_NORM_TOL
from slamreloc.io import limits as limits_module
from slamreloc.io.limits import InputLimits, set_limits
from tests.colmap_project import write_colmap_project

FRAME = struct.Struct("<II7dI")  # FRAME_ID RIG_ID rig_from_world NUM_DATA_IDS (frames.bin)
DATUM = struct.Struct("<iIQ")  # SENSOR_TYPE SENSOR_ID DATA_ID


@pytest.fixture(scope="module")
def source(scene_dir):
    """Three frames of each of the synthetic scene's first two sequences (7-Scenes layout)."""
    ds = load_dataset(scene_dir)
    return ds.frames("seq-01")[:3] + ds.frames("seq-02")[:3]


@pytest.fixture
def text_limit(monkeypatch):
    """set_limits for one test: the bounds in force before it come back after it."""
    monkeypatch.setattr(limits_module, "_current", None)
    return lambda n: set_limits(max_text_bytes=n)


def _refused(root: Path, match: str) -> str:
    """The one-line InputError that loading the project at `root` gives, matched against
    `match`."""
    with pytest.raises(InputError, match=match) as err:
        load_dataset(root)
    assert "\n" not in str(err.value)
    return str(err.value)


def _model(root: Path) -> Path:
    return root / "sparse" / "0"


# --- B1: a text model's memory -------------------------------------------------------------

def _one_image_with_points(root: Path, points: str) -> Path:
    """images.txt holding the project's first image line and `points` as its POINTS2D."""
    path = _model(root) / "images.txt"
    first = next(line for line in path.read_text().splitlines()
                 if line and not line.startswith("#"))
    path.write_text(f"{first}\n{points}\n")
    return path


def _peak_bytes(call) -> int:
    """The peak of Python's allocations (tracemalloc) while `call()` runs, in bytes."""
    tracemalloc.start()
    try:
        call()
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


@pytest.mark.parametrize("first", ["10.5", "1e100"])  # matched whole; read a word at a time
def test_a_long_points_line_is_checked_without_a_list_of_its_words(source, tmp_path, first):
    """B1: a POINTS2D line of 100 000 points (1.4 MB) took ~28 times its size (a str a word);
    now the check holds the file once. 1e100 is a number the fast pattern leaves to the
    word-at-a-time reading, which keeps no list either."""
    root = write_colmap_project(source, tmp_path / "p", "txt", legacy=True)
    path = _one_image_with_points(root, f"{first} 20.25 -1 " + "10.5 20.25 -1 " * 100_000)
    size = path.stat().st_size
    peak = _peak_bytes(lambda: check_model(_model(root), "txt"))
    assert peak < 3 * size, (peak, size)


def test_pycolmap_is_given_the_image_lines_without_their_points(source, tmp_path):
    """B1: pycolmap's reader holds a line twice and ~50 bytes a 2D point: it reads images.txt
    as the check read it, with its POINTS2D lines emptied (slamreloc uses no 2D point)."""
    root = write_colmap_project(source, tmp_path / "p", "txt", legacy=True)
    _one_image_with_points(root, "10.5 20.25 -1 " * 1000)
    index, rec = read_checked(_model(root), "txt")
    assert index.images_text is not None and b"20.25" not in index.images_text
    assert [im.num_points2D() for im in rec.images.values()] == [0]
    assert check_model(_model(write_colmap_project(source, tmp_path / "b", "bin")),
                       "bin").images_text is None


@pytest.mark.parametrize("points, match", [
    ("10 20 -1 " * 5000 + "nan 20 -1", r"images.txt:\d+: a 2D point coordinate is not a "
                                        r"number \('nan'"),
    ("10 20 -1 " * 5000 + "10 20", r"images.txt:\d+: expected X Y POINT3D_ID triples, got "
                                   "15002 values"),
    ("10 20 4294967295 " * 3 + "10 20 4294967296", r"images.txt:\d+: a POINT3D_ID out of "
                                                   r"range \(4294967296\)"),
    ("10 20 -2", r"a POINT3D_ID out of range \(-2\)"),
    ("1e400 20 -1", r"a 2D point coordinate is beyond the range of a number"),
    ("1" * 401 + " 20 -1", "a 2D point coordinate is a number of 401 characters"),
    ("10 20\xa0-1 -1", "a 2D point coordinate is not a number"),  # NBSP: no blank to COLMAP
], ids=["nan-at-the-end", "not-triples", "id-2^32", "id-2", "1e400", "401-digits", "nbsp"])
def test_a_bad_points_line_names_the_first_bad_value(source, tmp_path, points, match):
    """B1: the points line is matched by a compiled pattern, not split into words; what the
    pattern does not take is read a word at a time by the number rule, as before."""
    root = write_colmap_project(source, tmp_path / "p", "txt", legacy=True)
    _one_image_with_points(root, points)
    _refused(root, match)


def test_points_the_pattern_leaves_to_the_number_rule_are_taken(source, tmp_path):
    root = write_colmap_project(source, tmp_path / "p", "txt", legacy=True)
    _one_image_with_points(root, "1e100 +.5 4294967295 -0 7. -00001 1.5E-300 2 +12\r")
    assert len(load_dataset(root).frames("all")) == 1


def test_text_is_checked_as_utf8_a_chunk_at_a_time(tmp_path):
    """B1: read_text_bytes checks UTF-8 without a str of the whole file, a MiB at a time: a
    character across a chunk's end is taken, a bad byte is named at its offset in the file."""
    from slamreloc.io.fileio import UTF8_CHUNK, read_text, read_text_bytes

    path = tmp_path / "t.txt"
    text = "a" + "\u00e9\u20ac\U0001f600" * (UTF8_CHUNK // 5)  # 2-, 3-, 4-byte characters
    path.write_text(text, encoding="utf-8")
    assert read_text(path, "list", 1 << 30) == text
    data = path.read_bytes()
    damaged = data[:UTF8_CHUNK + 7] + b"\xff" + data[UTF8_CHUNK + 8:]
    path.write_bytes(damaged)
    with pytest.raises(UnicodeDecodeError) as whole:  # where decoding it all stops
        damaged.decode("utf-8")
    with pytest.raises(InputError, match=rf"t.txt: list is not UTF-8 text \(byte "
                                         rf"{whole.value.start}\)"):
        read_text_bytes(path, "list", 1 << 30)


# --- B2: max_text_bytes --------------------------------------------------------------------

def test_text_models_and_split_files_take_max_text_bytes(source, tmp_path, text_limit):
    """B2: COLMAP text models were bounded by a hard-coded 2 GiB and split files by 1 MiB,
    whatever `--limit max_text_bytes` said; now both take the documented bound."""
    assert InputLimits().max_text_bytes == 1 << 30  # docs/formats.md, "Bounds"
    root = write_colmap_project(source, tmp_path / "p", "txt", legacy=True)
    size = (_model(root) / "images.txt").stat().st_size
    text_limit(size - 1)
    _refused(root, rf"images.txt: COLMAP model file of {size} bytes, over the {size - 1} "
                   r"bytes limit \(max_text_bytes; raise it")
    text_limit(size)
    assert len(load_dataset(root).frames("all")) == 6
    (root / "TrainSplit.txt").write_text("seq-01\n" + "# a comment\n" * (size // 12))
    with pytest.raises(InputError, match=r"TrainSplit.txt: split file of .* over the .* limit "
                                         r"\(max_text_bytes"):
        load_dataset(root)
    text_limit(1 << 40)  # raised: a split file is no longer held to 1 MiB
    (root / "TrainSplit.txt").write_text("seq-01\n" + "#" * (2 << 20) + "\n")
    assert load_dataset(root).resolve_split("train") == ["seq-01"]


def test_rigs_and_frames_text_take_max_text_bytes(source, tmp_path, text_limit):
    root = write_colmap_project(source, tmp_path / "p", "txt")
    frames = _model(root) / "frames.txt"
    with frames.open("a") as f:
        f.write("#" * 10_000 + "\n")
    text_limit(max(p.stat().st_size for p in _model(root).iterdir() if p != frames) + 1)
    _refused(root, r"frames.txt: COLMAP model file of .*\(max_text_bytes")


# --- B3, B4: rigs and frames ---------------------------------------------------------------

def _frames_bin(path: Path) -> list[list]:
    """frames.bin's records as [frame_id, rig_id, 7 pose values, [data]] (written by
    `_write_frames_bin`)."""
    data = path.read_bytes()
    (n,), pos, out = struct.unpack_from("<Q", data), 8, []
    for _ in range(n):
        *head, n_data = FRAME.unpack_from(data, pos)
        pos += FRAME.size
        out.append([*head, [DATUM.unpack_from(data, pos + DATUM.size * k)
                            for k in range(n_data)]])
        pos += DATUM.size * n_data
    return out


def _write_frames_bin(path: Path, frames: list[list]) -> None:
    body = b"".join(FRAME.pack(*f[:-1], len(f[-1])) + b"".join(DATUM.pack(*d) for d in f[-1])
                    for f in frames)
    path.write_bytes(struct.pack("<Q", len(frames)) + body)


@pytest.fixture
def model312(source, tmp_path) -> Path:
    """A COLMAP >= 3.12 binary project (rigs.bin, frames.bin: one rig, a frame an image)."""
    return write_colmap_project(source, tmp_path / "p312", "bin")


def _edit_frames(root: Path, edit) -> None:
    path = _model(root) / "frames.bin"
    frames = _frames_bin(path)
    edit(frames)
    _write_frames_bin(path, frames)


def _set(frames, i, field, value):
    frames[i][field] = value


@pytest.mark.parametrize("edit, match", [
    (lambda f: f.clear(), r"frames.bin: image 1 \('seq-01/.*'\) is in no frame"),
    (lambda f: _set(f, 0, 9, [(0, 1, 999)]), "frames.bin: frame 1 names image 999, which "
                                             "images.bin does not have"),
    (lambda f: _set(f, 0, 9, [(7, 1, 1)]), "frames.bin: datum 1 of frame 1 has unknown sensor "
                                           "type '7'"),
    (lambda f: _set(f, 0, 9, [(0, 2, 1)]), "frames.bin: frame 1 names CAMERA 2, which its rig "
                                           "1 does not have"),
    (lambda f: f.append(list(f[0])), "frames.bin: frame id 1 appears twice"),
    (lambda f: _set(f, 1, 9, [(0, 1, 1)]), "frames.bin: image 1 is in frames 1 and 2"),
    (lambda f: _set(f, 0, 1, 77), "frames.bin: frame 1 names rig 77, which rigs.bin does not "
                                  "have"),
], ids=["no-frame", "no-such-image", "sensor-type-7", "sensor-not-in-rig", "frame-twice",
        "image-in-two-frames", "no-such-rig"])
def test_damaged_frames_name_frames_bin_and_the_problem(model312, edit, match):
    """B3: these were "not a readable COLMAP model (unordered_map::at)" or pycolmap's internal
    check text; each is now one line naming frames.bin and what is wrong."""
    _edit_frames(model312, edit)
    _refused(model312, match)


def test_rigs_without_frames_and_the_reverse_are_refused(model312, source, tmp_path):
    (_model(model312) / "frames.bin").unlink()
    _refused(model312, "incomplete COLMAP model: rigs.bin without frames.bin")
    text = write_colmap_project(source, tmp_path / "t", "txt")
    (_model(text) / "rigs.txt").unlink()
    _refused(text, "incomplete COLMAP model: frames.txt without rigs.txt")
    empty = write_colmap_project(source, tmp_path / "e", "txt", legacy=True)
    for name in ("rigs", "frames"):  # both, holding no record: a model before 3.12
        (_model(empty) / f"{name}.txt").write_text("# nothing\n")
    assert len(load_dataset(empty).frames("all")) == 6


def test_damaged_rigs_name_rigs_bin(model312):
    path = _model(model312) / "rigs.bin"
    good = path.read_bytes()  # 1 rig: RIG_ID 1, NUM_SENSORS 1, CAMERA 1
    assert good == struct.pack("<QIIiI", 1, 1, 1, 0, 1)
    for data, match in (
            (struct.pack("<QIIiI", 1, 1, 1, 0, 42), "rigs.bin: rig 1 names camera 42, which "
                                                    "cameras.bin does not have"),
            (struct.pack("<QIIiI", 1, 1, 1, 9, 1), "rigs.bin: sensor 1 of rig 1 has unknown "
                                                   "sensor type '9'"),
            (struct.pack("<QIIiIiIB", 1, 1, 2, 0, 1, 0, 1, 0), "rigs.bin: rig 1 holds CAMERA "
                                                               "1 twice"),
            (good + good[8:], "rigs.bin: 16 bytes after the last record"),
            (struct.pack("<QIIiIiIB", 1, 1, 2, 0, 1, 1, 5, 2), "rigs.bin: rig 1 of 1: HAS_POSE "
                                                               "of sensor 2 of rig 1 is 2")):
        path.write_bytes(data)
        _refused(model312, match)


@pytest.mark.parametrize("q, match", [
    ((0.0, 0.0, 0.0, 0.0), "quaternion norm 0, not 1"),
    ((float("nan"), 0.0, 0.0, 0.0), "non-finite pose"),
    ((2.0, 0.0, 0.0, 0.0), "quaternion norm 2, not 1"),
    ((1 + 1.1 * QUATERNION_NORM_TOL, 0.0, 0.0, 0.0), "quaternion norm 1.0011, not 1"),
])
def test_a_bad_frame_pose_is_blamed_on_frames_bin(model312, q, match):
    """B4: a zero, NaN or norm-2 quaternion in frames.bin was reported against images.bin
    (intact); it is now refused where it is, by the rule of every pose read."""
    _edit_frames(model312, lambda f: f[0].__setitem__(slice(2, 6), q))
    message = _refused(model312, f"frames.bin: frame 1 .*{match}")
    assert "images.bin" not in message


def test_frame_poses_take_the_image_poses_tolerance(model312):
    """B4: the same unit-quaternion rule (`unit_quaternion`, QUATERNION_NORM_TOL) as images.bin
    and the pose files: within the tolerance taken, beyond it refused (test above)."""
    scale = 1 + 0.9 * QUATERNION_NORM_TOL
    _edit_frames(model312, lambda f: f[0].__setitem__(slice(2, 6),
                                                       [v * scale for v in f[0][2:6]]))
    assert len(load_dataset(model312).frames("all")) == 6


def test_a_bad_rig_sensor_pose_is_blamed_on_rigs_bin(model312):
    rigs = _model(model312) / "rigs.bin"
    sensor = struct.pack("<iIB7d", 1, 5, 1, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)  # an IMU
    rigs.write_bytes(struct.pack("<QIIiI", 1, 1, 2, 0, 1) + sensor)
    _refused(model312, "rigs.bin: rig 1's sensor IMU 5 .*quaternion norm 0, not 1")


def test_frames_txt_is_checked_line_by_line(source, tmp_path):
    root = write_colmap_project(source, tmp_path / "t", "txt")
    path = _model(root) / "frames.txt"
    lines = path.read_text().splitlines()
    first = next(i for i, line in enumerate(lines) if not line.startswith("#"))
    words = lines[first].split()
    for change, match in (
            ({-1: "999"}, "frame 1 names image 999, which images.txt does not have"),
            ({-3: "LIDAR"}, "datum 1 of frame 1 has unknown sensor type 'LIDAR'"),
            ({2: "0", 3: "0", 4: "0", 5: "0"}, r"frame 1 \(QW QX QY QZ\): quaternion norm 0"),
            ({9: "2"}, "the line ends before the type of datum 2 of frame 1")):
        edited = list(words)
        for k, v in change.items():
            edited[k] = v
        path.write_text("\n".join(lines[:first] + [" ".join(edited)] + lines[first + 1:]))
        _refused(root, rf"frames.txt:{first + 1}: {match}")


# --- B5: what an image of the model is -----------------------------------------------------

@pytest.mark.parametrize("make, kind", [
    (os.mkfifo, "a named pipe"),
    (lambda p: os.symlink("/dev/zero", p), "a device"),
    (os.mkdir, "a folder"),
])
def test_an_image_that_is_no_file_is_said_to_be_what_it_is(source, tmp_path, make, kind):
    """B5: a named pipe or a link to /dev/zero was "image file not found"."""
    root = write_colmap_project(source, tmp_path / "p", "bin", legacy=True)
    image = root / "images" / "seq-01" / source[0].image_path.name
    image.unlink()
    make(image)
    message = _refused(root, rf"{image}: image is not a regular file \({kind}\)")
    assert "not found" not in message and "images.bin" in message


def test_a_missing_image_is_still_not_found(source, tmp_path):
    root = write_colmap_project(source, tmp_path / "p", "bin", legacy=True)
    image = root / "images" / "seq-01" / source[0].image_path.name
    image.unlink()
    _refused(root, rf"{image}: image file not found \(listed in .*images.bin\)")


# --- B6: image names -----------------------------------------------------------------------

def _rename_first_image(root: Path, name: str) -> None:
    path = _model(root) / "images.txt"
    lines = path.read_text().splitlines()
    first = next(i for i, line in enumerate(lines) if line and not line.startswith("#"))
    words = lines[first].split()
    lines[first] = " ".join(words[:9] + [name])
    path.write_text("\n".join(lines) + "\n")


def test_image_names_in_images_txt_have_the_bin_bound(source, tmp_path):
    """B6: a 5000-byte name in images.txt became a bare OSError (File name too long) from
    load_dataset; it is refused as images.bin refuses one, naming the file and line."""
    root = write_colmap_project(source, tmp_path / "p", "txt", legacy=True)
    _rename_first_image(root, "seq-01/" + "a" * 5000)
    _refused(root, rf"images.txt:\d+: the name of image 1 is longer than {MAX_NAME_BYTES} "
                   "bytes")
    _rename_first_image(root, "seq-01/" + "\u00e9" * (MAX_NAME_BYTES // 2))  # 2 bytes each
    _refused(root, f"longer than {MAX_NAME_BYTES} bytes")
    binary = write_colmap_project(source, tmp_path / "b", "bin", legacy=True)
    path = _model(binary) / "images.bin"
    path.write_bytes(path.read_bytes().replace(b"seq-01/", b"seq-01/" + b"a" * 5000, 1))
    _refused(binary, f"images.bin: the name of image 1 of 6 is longer than {MAX_NAME_BYTES} "
                     "bytes")


def test_a_name_within_the_bound_but_too_long_for_the_file_system(source, tmp_path):
    """B6: a name under 4096 bytes whose file name is over the file system's 255: an
    InputError naming images.txt, not an OSError."""
    root = write_colmap_project(source, tmp_path / "p", "txt", legacy=True)
    _rename_first_image(root, "seq-01/" + "a" * 300)
    _refused(root, r"cannot read image \(File name too long\) \(listed in .*images.txt\)")
