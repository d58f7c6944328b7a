"""Issue 43, attack round 21 (CLI side): outputs aimed at inputs through a second name (a bind
mount), one pose and one split rule for every reader, frame order, comments in written files,
dataset files that contradict each other, bound names, multi-page images."""

from __future__ import annotations

import os
import shutil
import subprocess

import numpy as np
import pytest

from slamreloc.datasets import load_dataset
from slamreloc.errors import InputError


@pytest.fixture(scope="module")
def tiny_map(tmp_path_factory):
    from tests.test_fuzz_inputs import _tiny_map

    return _tiny_map(tmp_path_factory.mktemp("round21") / "map")


def test_a_second_name_for_an_input_is_the_input(tmp_path):
    """W1, W2: outputs were compared with inputs by their resolved names only, so an output
    named through a bind mount of the input's folder replaced the input map (`pseudo-label
    --out`, `slam --out`) or wrote inside the dataset (`evaluate --report`, `map --out`).
    `relation_on_disk` (outputs against inputs) also compares what the names are on disk
    (a hard link here: no root)."""
    from slamreloc.io.fileio import relation_on_disk as relation
    from slamreloc.io.fileio import resolved

    folder = tmp_path / "data"
    folder.mkdir()
    (folder / "a.txt").write_text("mine")
    os.link(folder / "a.txt", tmp_path / "b.txt")
    assert relation(resolved(tmp_path / "b.txt"), resolved(folder / "a.txt")) == "is"
    assert relation(resolved(tmp_path / "c.txt"), resolved(folder / "a.txt")) is None
    assert relation(resolved(folder / "new" / "x"), resolved(folder)) == "lies inside"
    assert relation(resolved(tmp_path), resolved(folder / "a.txt")) == "would hold"


def test_outputs_through_a_bind_mount_of_an_input_are_refused(tiny_map, scene_dir, tmp_path):
    """W1, W2 through the CLI, where a bind mount can be made (root in a mount namespace)."""
    from tests.fuzzing import run_cli

    alias = tmp_path / "alias"
    alias.mkdir()
    if subprocess.run(["mount", "--bind", str(tiny_map.parent), str(alias)],
                      capture_output=True).returncode:
        pytest.skip("cannot mount --bind here (needs root and a mount namespace)")
    try:
        before = {p.name: p.read_bytes() for p in tiny_map.iterdir() if p.is_file()}
        code, err = run_cli(["slam", str(scene_dir), "--map", str(tiny_map), "--split",
                             "seq-02", "--report", str(tmp_path / "r.json"), "--out",
                             str(alias / tiny_map.name)])
        assert code == 2 and "--out is the map" in err.strip().splitlines()[-1], err
        assert {p.name: p.read_bytes() for p in tiny_map.iterdir() if p.is_file()} == before
    finally:
        subprocess.run(["umount", str(alias)], check=True)


def test_report_poses_follow_the_pose_files_rule(tmp_path):
    """W3: a pseudo-label report's pose with its rotation scaled by 1.003 was drawn by `view`
    (tolerance 1e-2) while the same matrix in a pose file is refused (RIGID_TOL, 1e-3)."""
    from slamreloc.viewer.reports import read_pseudo_label

    m = np.eye(4)
    m[:3, :3] *= 1.003
    path = tmp_path / "pl.json"
    with pytest.raises(InputError, match="not orthonormal|not a rigid"):
        read_pseudo_label(path, {"poses": {"seq-01/frame-000000": m.tolist()}})
    assert read_pseudo_label(path, {"poses": {"seq-01/frame-000000": np.eye(4).tolist()}})


def test_a_frame_listed_twice_is_refused_by_the_viewer(scene_dir, tmp_path):
    """W4: an evaluate report listing a frame twice in per_query was drawn; W5: a trajectory
    whose names file gives one frame two poses was drawn with the first (`evaluate
    --reference` refuses it: one rule, `poses_by_name`)."""
    from slamreloc.geometry import Rigid3, write_tum_trajectory
    from slamreloc.viewer.reports import read_evaluate
    from slamreloc.viewer.trajectories import read_trajectory

    dataset = load_dataset(scene_dir)
    query = {"name": "seq-02/frame-000000", "translation_error_m": 0.01,
             "rotation_error_deg": 0.1, "num_inliers": 50}
    with pytest.raises(InputError, match=r"per_query\[1\]\.name: frame 'seq-02/frame-000000' "
                                         "is listed twice"):
        read_evaluate(tmp_path / "r.json", {"per_query": [query, query]}, dataset, [])
    path = tmp_path / "t.tum"
    write_tum_trajectory(path, [0, 1], [Rigid3.identity(), Rigid3.identity()],
                         names=["seq-01/frame-000000", "seq-01/frame-000000"])
    with pytest.raises(InputError, match="frame 'seq-01/frame-000000' has more than one pose"):
        read_trajectory(path)


@pytest.mark.parametrize("lines,words", [
    ("sequence1\nsequence1\n", "names seq-01 twice"),
    ("sequence1\nsequence01\n", "names seq-01 twice"),
    ("sequence\u0661\n", "expected lines like 'sequence1'"),
])
def test_split_files_name_each_sequence_once_in_ascii_digits(scene_dir, tmp_path, lines, words):
    """W6: a split file naming a sequence twice was merged unsaid (`--split seq-01,seq-01` is
    refused); W7: other scripts' digits were read as numbers (`\\d` is any Unicode digit)."""
    root = tmp_path / "scene"
    shutil.copytree(scene_dir, root)
    (root / "TrainSplit.txt").write_text(lines, encoding="utf-8")
    with pytest.raises(InputError, match=words):
        load_dataset(root).frames("train")


def test_frames_numbered_without_zeros_keep_their_order(scene_dir, tmp_path):
    """W8: frames named frame-0 ... frame-19 were ordered as text (frame-10 second), so
    `slam` tracked the sequence out of order."""
    root = tmp_path / "scene"
    shutil.copytree(scene_dir, root)
    for path in sorted((root / "seq-01").glob("frame-*")):
        stem, rest = path.name.split(".", 1)
        path.rename(path.with_name(f"frame-{int(stem[6:])}.{rest}"))
    names = [f.name for f in load_dataset(root).frames("seq-01")]
    assert names[:3] == ["seq-01/frame-0", "seq-01/frame-1", "seq-01/frame-2"], names[:12]
    assert names == sorted(names, key=lambda n: int(n.rsplit("-", 1)[1]))


def test_comments_of_written_trajectories_hold_any_path(tmp_path):
    """W9: a map path that is not UTF-8 failed `export --tum` and `slam --trajectory` at the
    very end ('utf-8' codec can't encode); W10: a path with a line break wrote a pose row of
    its own into the TUM header."""
    from slamreloc.geometry import Rigid3, read_named_trajectory, write_tum_trajectory

    path = tmp_path / "t.tum"
    name = os.fsdecode(b"/m\xfe")  # a file name that is not UTF-8, as Python holds it
    write_tum_trajectory(path, [0.0], [Rigid3.identity()],
                         [f"map {name}\n99.0 1 2 3 0 0 0 1\n#"])
    lines = path.read_text().splitlines()
    assert len(lines) == 2 and lines[0].startswith("# map /m\\udcfe\\n99.0"), lines
    assert len(read_named_trajectory(path).poses) == 1


def test_a_camera_txt_and_intrinsics_txt_that_disagree_are_refused(scene_dir, tmp_path):
    """W11: with both files, intrinsics.txt was ignored unsaid (a COLMAP model whose .bin and
    .txt disagree is refused); files that agree are taken."""
    root = tmp_path / "scene"
    shutil.copytree(scene_dir, root)
    k = np.loadtxt(root / "intrinsics.txt") if (root / "intrinsics.txt").exists() else None
    if k is None:
        pytest.skip("the synthetic scene has no intrinsics.txt")
    camera = load_dataset(root).frames("seq-01")[0].camera
    (root / "camera.txt").write_text(camera.colmap_string() + "\n")  # COLMAP's convention
    assert load_dataset(root).frames("seq-01")[0].camera.pinhole.params() == \
        pytest.approx(camera.pinhole.params())
    (root / "camera.txt").write_text(camera.colmap_string().replace(f" {k[0, 0]:g}", " 100", 1)
                                     + "\n")
    with pytest.raises(InputError, match="camera.txt: camera .* and .*intrinsics.txt .* "
                                         "disagree; keep one"):
        load_dataset(root)


def test_a_tum_depth_list_naming_one_image_twice_is_refused(tmp_path):
    """W12: depth.txt giving one depth image to two instants was taken (rgb.txt refuses a
    repeat)."""
    (tmp_path / "rgb.txt").write_text("1.0 rgb/1.png\n2.0 rgb/2.png\n")
    (tmp_path / "depth.txt").write_text("1.0 depth/1.png\n2.0 depth/1.png\n")
    with pytest.raises(InputError, match=r"depth\.txt: image 'depth/1\.png' is listed more"):
        load_dataset(tmp_path)


def test_bound_names_are_read_exactly(tiny_map, tmp_path):
    """W13: `--limit ' max_image_pixels =N'` was taken though blanks around the value are
    refused, and a misspelt SLAMRELOC_MAX_IMAG_PIXELS was ignored unsaid."""
    import sys

    from slamreloc.io.limits import parse_limits

    with pytest.raises(InputError, match="expected NAME=VALUE"):
        parse_limits([" max_image_pixels =1000000"])
    assert parse_limits(["max-image-pixels=1000000"]) == {"max_image_pixels": 1000000}
    done = subprocess.run([sys.executable, "-m", "slamreloc.cli", "export", str(tiny_map),
                           "--tum", str(tmp_path / "t.tum")], capture_output=True, text=True,
                          env={**os.environ, "SLAMRELOC_MAX_IMAG_PIXELS": "5"}, timeout=300)
    assert done.returncode == 2 and done.stderr.strip().splitlines()[-1].startswith(
        "error: environment variable SLAMRELOC_MAX_IMAG_PIXELS names no bound"), done.stderr
    assert not (tmp_path / "t.tum").exists()


def test_a_multi_page_image_is_refused(tmp_path):
    """W14: a TIFF of pages of other sizes was read as its first page, unsaid."""
    from PIL import Image

    from slamreloc.io.images import read_image

    pages = [Image.new("RGB", size) for size in ((320, 240), (640, 480))]
    pages[0].save(tmp_path / "m.tif", save_all=True, append_images=pages[1:])
    with pytest.raises(InputError, match="m.tif: a TIFF image of more than one page"):
        read_image(tmp_path / "m.tif")
    pages[0].save(tmp_path / "one.tif")
    assert read_image(tmp_path / "one.tif").shape == (240, 320, 3)
