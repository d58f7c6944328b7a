"""Issue 43, attack round 25's notes and round 26: a command that fails writes no empty folders
(`outputs.make_parents` / `remove_made`); a server started on a learned maps' folder cleans what
a server killed while saving there left (`map.lock.clean_maps_folder`), and nothing else."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from slamreloc.service.server import ServeConfig, start_server
from tests.fuzzing import run_cli
from tests.test_cli_round5 import one_line_exit_2


def test_a_failed_pseudo_label_leaves_no_folders_it_made(small_map, scene_dir, tmp_path):
    """Round 25, N5: `pseudo-label --out a/b/c/new` failing at the dataset's split left the
    empty folders a/b/c it had made."""
    kept = tmp_path / "kept"
    kept.mkdir()
    out = kept / "a" / "b" / "c" / "new"
    one_line_exit_2(["pseudo-label", str(small_map.root), str(scene_dir), "--out", str(out),
                     "--report", str(kept / "r" / "r.json"), "--split", "seq-09"],
                    "unknown split")
    assert sorted(os.listdir(kept)) == []  # the folder that was there is kept, empty


def test_a_file_output_made_in_new_folders_keeps_them(small_map, tmp_path):
    """The other side: outputs written into folders the command made keep those folders."""
    tum, ply = tmp_path / "x" / "y" / "t.tum", tmp_path / "p" / "q" / "c.ply"
    code, err = run_cli(["export", str(small_map.root), "--tum", str(tum), "--ply", str(ply)])
    assert code == 0, err
    assert tum.is_file() and ply.is_file()


_KILLED_SAVE = """
import os, shutil, signal, sys
from pathlib import Path
from slamreloc.map.lock import map_write_lock
from slamreloc.io.outputs import temp_dir_path
seed, out = Path(sys.argv[1]), Path(sys.argv[2])
with map_write_lock(out):
    shutil.copytree(seed, temp_dir_path(out))  # the new map, half written
    os.kill(os.getpid(), signal.SIGKILL)
"""


def test_a_server_cleans_a_save_a_killed_server_left(small_map, tmp_path):
    """Round 25, N4: a server killed while writing learned map NAME left `.NAME.lock` and
    `.NAME.tmp-PID/` (a regressor each) until a session saved NAME again; a name never saved
    again kept them for good. The next server on that folder cleans them at start; a user's
    hidden files of like names are kept."""
    folder = tmp_path / "learned"
    folder.mkdir()
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    proc = subprocess.run([sys.executable, "-c", _KILLED_SAVE, str(small_map.root),
                           str(folder / "k")], env=env, capture_output=True, timeout=120)
    assert proc.returncode == -signal.SIGKILL, proc.stderr
    debris = sorted(os.listdir(folder))
    assert debris[0] == ".k.lock" and debris[1].startswith(".k.tmp-"), debris
    (folder / ".notes.lock").write_text("2024\nbudget\n")  # a user's, not a writer's record
    (folder / ".photos.tmp-123").mkdir()
    (folder / ".photos.tmp-123" / "me.jpg").write_bytes(b"\xff\xd8 a photo")
    running = start_server({}, ServeConfig(port=0, watch_s=0, learned_maps=folder))
    try:
        assert sorted(os.listdir(folder)) == [".notes.lock", ".photos.tmp-123"]
        assert (folder / ".notes.lock").read_text() == "2024\nbudget\n"
    finally:
        running.stop()
    shutil.rmtree(folder)


# ---- round 25, N3: a POINTS2D line's fast check ----------------------------------------------
_DIGITS = st.text("0123456789", min_size=1, max_size=4)
_COORD = st.builds(lambda sign, whole, frac, exp: f"{sign}{whole}{frac}{exp}",
                   st.sampled_from(["", "-", "+"]), _DIGITS,
                   st.sampled_from(["", ".", ".5", ".25"]),
                   st.sampled_from(["", "e0", "e-7", "e+38", "e99", "e100", "e150", "e199",
                                    "e200", "e308", "e400", "E-400", "e-999"]))
_ID = st.sampled_from(["-1", "0", "7", "+3", "-2", "4294967295", "123456789", "1234567890"])


@given(st.lists(st.tuples(_COORD, _COORD, _ID), min_size=1, max_size=6))
@settings(max_examples=300, deadline=None)
def test_the_fast_points2d_check_takes_only_what_the_word_rule_takes(triples):
    """A POINTS2D line is matched whole by one pattern where it can be (3-digit exponents now
    included: a 45 MB line of them took 13.5 s word by word); what the pattern takes, the
    number rule applied a word at a time must take too (finite, ids in range)."""
    from slamreloc.datasets.colmap_check import _PLAIN_POINTS, _check_points

    line = " ".join(" ".join(t) for t in triples).encode()
    if _PLAIN_POINTS.fullmatch(line):
        for x, y, point3d_id in triples:
            assert np.isfinite(float(x)) and np.isfinite(float(y))
            assert -1 <= int(point3d_id) < 2 ** 32
        _check_points(Path("images.txt"), 1, line, 0, len(line))  # the same verdict


# ---- round 26, F1: a lens that folds sideways -----------------------------------------------
@pytest.mark.parametrize("cx", ["160", "5.5", "-9.5"])
def test_a_lens_folding_off_the_axes_is_refused(cx):
    """F1: tangential terms fold the mapping off the four axis rays the check walked: an
    OPENCV lens whose pixels inside the inscribed circle have two directions was taken.
    Round 27, G1: with the principal point off centre (or outside the image) the circle
    around it was tiny or empty, and the same lens was taken: the circle is the image's."""
    code, err = run_cli(["localize", "no-map", "x.png", "--camera",
                         f"OPENCV 320 240 200 200 {cx} 120 0.28 0.16 -0.29 -0.36"])
    assert code == 2 and err.strip().splitlines()[-1].startswith(
        "error: --camera: its distortion [0.28, 0.16, -0.29, -0.36] folds back inside the "
        "image (near pixel"), err


@given(st.sampled_from(["OPENCV", "FULL_OPENCV", "OPENCV_FISHEYE", "RADIAL"]),
       st.lists(st.floats(-0.6, 0.6), min_size=8, max_size=8),
       st.sampled_from([159.5, 100.0, 20.0, -9.5]))
@settings(max_examples=80, deadline=None)
def test_a_lens_taken_undistorts_every_pixel_of_its_circle(model, values, cx):
    """Every pixel inside the circle inscribed in the image, for a lens the check takes,
    comes back to itself through undistortion (one direction each), wherever the principal
    point lies."""
    from slamreloc.camera_models import (
        distort_normalized,
        fold_problem,
        n_distortion,
        undistort_normalized,
    )

    distortion = tuple(values[:n_distortion(model)])
    f, cy = 200.0, 119.5
    if fold_problem(model, distortion, 320, 240, f, f, cx, cy):
        return
    angles = np.linspace(0, 2 * np.pi, 90, endpoint=False)
    radius = np.linspace(0, 119.5, 40)[:, None]  # the circle inscribed in 320 x 240
    pixels = np.stack([159.5 + radius * np.cos(angles), 119.5 + radius * np.sin(angles)],
                      -1).reshape(-1, 2) - [cx, cy]
    ideal = undistort_normalized(model, distortion, pixels / f)
    back = distort_normalized(model, distortion, ideal) * f
    assert np.abs(back - pixels).max() < 0.05


# ---- round 26, F2, F3, F9: a video's name ---------------------------------------------------
def _video(path: Path) -> Path:
    import cv2

    writer = cv2.VideoWriter(os.fsdecode(path), cv2.VideoWriter_fourcc(*"MJPG"), 10, (64, 48))
    for i in range(4):
        writer.write(np.full((48, 64, 3), 40 * i, np.uint8))
    writer.release()
    return path


@pytest.mark.parametrize("name, problem", [
    ("..avi", "is not a plain relative path"),
    ("...avi", "is not a path inside the dataset"),
    ("a\nb.avi", "holds a line break"),
    ("a\udcffb.avi", "holds a line break or another control character"),
])
def test_a_video_whose_name_cannot_name_its_frames_is_refused(tmp_path, name, problem):
    """F2, F3, F9: a video named `..avi` gave a raw "File exists" naming the temporary, one
    with a line break wrote a dataset nothing reads, one not UTF-8 crashed OpenCV (SIGSEGV)."""
    made = _video(tmp_path / "v.avi")
    video = tmp_path / name
    os.rename(made, video)
    code, err = run_cli(["sfm", str(video), "--out", str(tmp_path / "out"), "--fps", "10"])
    last = err.strip().splitlines()[-1]
    assert code == 2 and "its frames are named after the video" in last and problem in last
    assert sorted(os.listdir(tmp_path)) == [name]


def test_a_video_in_a_folder_not_utf8_is_one_error(tmp_path):
    """F9: OpenCV's video reader crashed the process on a path that is not UTF-8 text."""
    from slamreloc.errors import InputError
    from slamreloc.io.video import video_frames

    folder = Path(os.fsdecode(bytes(tmp_path) + b"/d\xff"))
    folder.mkdir()
    video = _video(tmp_path / "v.avi").rename(folder / "v.avi")
    with pytest.raises(InputError, match="its path is not UTF-8 text"):
        video_frames(video, 10)


def test_a_scene_renders_into_a_folder_not_utf8(tmp_path):
    """F9: `demo --workdir $'dw\\xff'` crashed in OpenCV's image writer; frames are written
    through Python's file API."""
    from slamreloc.io.images import read_image, write_image

    folder = Path(os.fsdecode(bytes(tmp_path) + b"/w\xff"))
    folder.mkdir()
    pixels = np.arange(48 * 64 * 3, dtype=np.uint8).reshape(48, 64, 3)
    write_image(folder / "a.png", pixels)
    assert np.array_equal(read_image(folder / "a.png"), pixels[:, :, ::-1])


# ---- round 26, F6: a checkpoint's moments and weights ---------------------------------------
def _checkpoint(tmp_path):
    from slamreloc.regressor.train import train_regressor
    from tests.test_resume import CONFIG, _data, _model

    desc, points = _data()
    ckpt = tmp_path / "ckpt.pt"
    train_regressor(_model(), desc, points, CONFIG, "cpu", progress=False, checkpoint=ckpt)
    return ckpt, lambda: train_regressor(_model(), desc, points, CONFIG, "cpu",
                                         progress=False, checkpoint=ckpt, resume=True)


def test_a_checkpoint_of_moments_no_training_reaches_is_refused(tmp_path):
    """F6: Adam first moments of 1e30 (finite, of the right shape and sign) trained the whole
    run, then were blamed on the map's metadata. |m| <= sqrt(C v) holds for every state Adam
    reaches from zero."""
    import torch

    from slamreloc.errors import InputError

    ckpt, resume = _checkpoint(tmp_path)
    state = torch.load(ckpt, weights_only=True)
    for moments in state["optimizer"]["state"].values():
        moments["exp_avg"].fill_(1e30)
    torch.save(state, ckpt)
    with pytest.raises(InputError, match=rf"^{ckpt}: unreadable training checkpoint "
                                         r"\('optimizer': a first moment larger than its "
                                         r"second moment allows\)$"):
        resume()


def test_a_checkpoint_whose_training_diverges_is_named(tmp_path):
    """F6: weights x 1e30 (finite) made the loss infinite; the error came after the run and
    named the map's metadata. Training stops at the first epoch whose loss is not finite, and
    after a resume names the checkpoint. The checkpoint is one a Ctrl-C at the end of epoch 3
    saved (it resumes: epoch 4)."""
    import torch

    from slamreloc.errors import Diverged, Interrupted
    from slamreloc.regressor.train import train_regressor
    from tests.test_resume import CONFIG, _data, _model

    desc, points = _data()
    ckpt = tmp_path / "ckpt.pt"

    def ctrl_c(epoch, loss):
        if epoch == 2:
            raise KeyboardInterrupt

    with pytest.raises(Interrupted, match="interrupted at epoch 4/6"):
        train_regressor(_model(), desc, points, CONFIG, "cpu", progress=False,
                        checkpoint=ckpt, on_epoch_end=ctrl_c)
    state = torch.load(ckpt, weights_only=True)
    assert state["epoch"] == 3 and len(state["losses"]) == 3
    for t in state["model"].values():
        if t.is_floating_point():
            t.mul_(1e30)
    torch.save(state, ckpt)
    with pytest.raises(Diverged) as err:
        train_regressor(_model(), desc, points, CONFIG, "cpu", progress=False,
                        checkpoint=ckpt, resume=True)
    assert str(err.value).startswith(f"{ckpt}: training resumed from this checkpoint "
                                     "diverged at epoch 4/6"), err.value


def test_training_that_diverges_stops_at_that_epoch():
    from slamreloc.errors import Diverged
    from slamreloc.regressor.train import train_regressor
    from tests.test_resume import CONFIG, _data, _model

    desc, points = _data()
    with pytest.raises(Diverged, match=r"^training diverged at epoch \d/6: its loss is no "
                                       r"longer a finite number \(lower `lr`"):
        train_regressor(_model(), desc, points, replace(CONFIG, lr=1e38), "cpu",
                        progress=False)


# ---- round 26, F8, F10: one rule for a pose file --------------------------------------------
def test_a_frame_given_two_poses_under_two_of_its_names_is_refused(scene_dir, tmp_path):
    """F8: `seq-01/frame-000000` and `seq-01/frame-000000.color.png` (its image) with
    different poses: one was kept without a word, while a name given twice is refused."""
    from slamreloc.datasets import load_dataset
    from slamreloc.errors import InputError
    from slamreloc.geometry import Rigid3, tum_line

    frames = load_dataset(scene_dir).frames("all")
    first = frames[0]
    image = Path(first.image_path).relative_to(scene_dir).as_posix()
    moved = Rigid3(first.world_from_cam.rotation, first.world_from_cam.translation + [0.5, 0, 0])
    lines = [tum_line(f.name, f.world_from_cam) for f in frames]
    path = tmp_path / "poses.txt"
    path.write_text("\n".join(lines + [tum_line(image, first.world_from_cam)]) + "\n")
    assert load_dataset(scene_dir, path).frames("all")[0].world_from_cam is not None  # agree
    path.write_text("\n".join(lines + [tum_line(image, moved)]) + "\n")
    with pytest.raises(InputError) as err:
        load_dataset(scene_dir, path)
    assert str(err.value) == (f"{path.resolve()}: gives frame {first.name!r} two poses, as "
                              f"{first.name!r} and as {image!r} (0.5 m and 0 deg apart); give "
                              "each frame one pose")


def test_odometry_from_a_file_follows_the_poses_rule(scene_dir, small_map, tmp_path):
    """F10: a TUM file of stamps two sequences share: `--poses` refused it, `--odometry` gave
    seq-02's frames seq-01's poses. Both now match the file to the frames by one rule."""
    from slamreloc.datasets import load_dataset
    from slamreloc.geometry import write_tum_trajectory

    frames = load_dataset(scene_dir).frames("seq-01")
    path = tmp_path / "odo.txt"
    write_tum_trajectory(path, [f.timestamp for f in frames], [f.world_from_cam for f in frames])
    argv = ["slam", str(scene_dir), "--map", str(small_map.root), "--split", "seq-01,seq-02",
            "--report", str(tmp_path / "r.json")]
    for option in ("--poses", "--odometry"):
        code, err = run_cli([*argv, option, str(path)])
        assert code == 2 and "is a frame of both seq-01 and seq-02; name the frames" in err, err
    short = tmp_path / "short.txt"  # the first 10 frames: said before any work
    write_tum_trajectory(short, [f.timestamp for f in frames[:10]],
                         [f.world_from_cam for f in frames[:10]])
    code, err = run_cli([*argv[:5], "seq-01", *argv[6:], "--odometry", str(short)])
    assert code == 2 and (f"{short}: no pose for frame {frames[10].name} (timestamp "
                          f"{frames[10].timestamp:.6f}), number 11 of the 60 tracked") in err, err


# ---- round 26, E2, E3: what an image header says --------------------------------------------
def test_a_16_bit_pgm_cut_short_is_said_to_be_corrupt(tmp_path):
    """E2: Pillow's mode of a 16-bit PGM ("I") was read as 32-bit samples, and a truncated
    one was refused as "32-bit PNM samples, which OpenCV does not decode"."""
    from slamreloc.errors import InputError
    from slamreloc.io.images import encoded_header, read_image

    data = b"P5\n320 240\n65535\n" + b"\1" * (320 * 240 * 2)
    header = encoded_header(data, "x.pgm")
    assert (header.channels, header.bits, header.format) == (1, 16, "PNM")
    cut = tmp_path / "cut.pgm"
    cut.write_bytes(data[:-1000])
    with pytest.raises(InputError, match=r"cut.pgm: not a readable image \(empty or corrupt\)$"):
        read_image(cut)


def _bmp_saying(width: int, height: int) -> bytes:
    """A real 1-bit BMP's header, its size fields made to say width x height."""
    import io
    import struct

    from PIL import Image

    out = io.BytesIO()
    Image.new("1", (8, 8)).save(out, "BMP")
    data = bytearray(out.getvalue())
    data[18:26] = struct.pack("<ii", width, height)
    return bytes(data)


@pytest.mark.parametrize("make", [lambda: _bmp_saying(14000, 14000),
                                  lambda: b"P5\n20000 10000\n255\n" + b"\0" * 64],
                         ids=["bmp", "pgm"])
def test_every_format_meets_the_one_pixel_bound(make):
    """E3: over Pillow's own bound (~179 MP) a BMP, PNM, TIFF or WebP was "not a readable
    image (DecompressionBombError)", where a PNG or JPEG is over `max_image_pixels`, which
    a user may raise."""
    from slamreloc.errors import InputError
    from slamreloc.io import limits
    from slamreloc.io.images import encoded_header

    with pytest.raises(InputError, match=r"^x: image is \d+x\d+ = \d+\.\d MP, over the "
                                         r"16\.8 MP limit \(max_image_pixels"):
        encoded_header(make(), "x")
    old = limits.limits()
    try:
        limits.set_limits(max_image_pixels=300_000_000)
        header = encoded_header(make(), "x")
    finally:
        limits.set_limits(max_image_pixels=old.max_image_pixels)
    assert header.width * header.height in (196_000_000, 200_000_000)


# ---- round 26, E4: options of `serve --engine ray` ------------------------------------------
def test_ray_serve_takes_watch_and_request_bound(small_map, tmp_path, monkeypatch):
    """E4: `--engine ray` dropped `--watch` and `--max-request-mb` (and `--workers`, the
    session bounds) without a word: a 2 MiB request was answered under `--max-request-mb 1`,
    and a replaced map reloaded under `--watch 0`."""
    pytest.importorskip("ray")
    from slamreloc.service import ray_serve

    token = tmp_path / "token.txt"
    token.write_text("a-token-of-enough-characters\n")
    argv = ["serve", str(small_map.root), "--engine", "ray", "--token-file", str(token),
            "--port", "0"]
    for extra in (["--workers", "2"], ["--max-sessions", "3"]):
        code, err = run_cli([*argv, *extra])
        assert code == 2 and f"--engine ray: {extra[0]} applies to --engine grpc only" in err
    code, err = run_cli(["serve", str(small_map.root), "--replicas", "2", "--port", "0"])
    assert code == 2 and "--replicas applies to --engine ray only" in err, err
    seen = {}

    def deploy(maps, replicas, host, port, **kwargs):
        seen.update(kwargs, replicas=replicas)

    def block():
        raise KeyboardInterrupt

    monkeypatch.setattr(ray_serve, "deploy", deploy)
    monkeypatch.setattr(ray_serve, "_block", block)
    monkeypatch.setattr(ray_serve, "shutdown", lambda: None)
    code, err = run_cli([*argv, "--watch", "0", "--max-request-mb", "1", "--replicas", "2"])
    assert code == 0, err
    assert seen == {"token": "a-token-of-enough-characters", "watch_s": 0.0,
                    "max_request_bytes": 1 << 20, "replicas": 2}


def test_an_empty_file_beside_a_trajectory_output_is_not_a_trajectory(tmp_path):
    """Round 26's note: `slam ... --trajectory run.txt > run.out` made an empty run.out, which
    read as a TUM trajectory sharing run.names.txt, and the run was refused."""
    from slamreloc.datasets.poses import check_names_sidecar_free
    from slamreloc.errors import InputError

    (tmp_path / "run.out").write_text("")
    check_names_sidecar_free(tmp_path / "run.txt", "--trajectory")
    (tmp_path / "run.out").write_text("0.000000 0 0 0 0 0 0 1\n")
    with pytest.raises(InputError, match="also names the stamps of the trajectory"):
        check_names_sidecar_free(tmp_path / "run.txt", "--trajectory")


# ---- round 27, G3, G4: samples wider than 16 bits -------------------------------------------
def _float_images(tmp_path):
    import cv2

    grey = (np.arange(64 * 48).reshape(48, 64) % 255 / 255).astype(np.float32)
    pfm = tmp_path / "g.pfm"
    pfm.write_bytes(b"Pf\n64 48\n-1.0\n" + np.flipud(grey).astype("<f4").tobytes())
    colour = tmp_path / "c.tif"
    cv2.imwrite(str(colour), np.dstack([grey] * 3))
    return {"grey PFM": pfm, "colour float TIFF": colour}


def test_images_of_float_samples_are_refused_saying_so(tmp_path):
    """G3: a float PFM was decoded with a saturating cast to 8 bits (a black picture, taken);
    G4: a float colour TIFF was "unknown format" though TIFF is read."""
    from slamreloc.errors import InputError
    from slamreloc.io.images import read_image

    files = _float_images(tmp_path)
    with pytest.raises(InputError, match=r"g\.pfm: not a readable image \(32-bit PNM samples, "
                                         r"which OpenCV does not decode; save it with 8 or 16 "
                                         r"bits\)$"):
        read_image(files["grey PFM"])
    with pytest.raises(InputError, match=r"c\.tif: not a readable image \(a TIFF whose layout "
                                         r"or samples are not read, which its header reader "
                                         r"cannot parse: e\.g\. float or 32-bit colour "
                                         r"samples, 16-bit grey with alpha, or a damaged "
                                         r"header; save it with 8 or 16 bits\)$"):
        read_image(files["colour float TIFF"])


# ---- round 27, G5: the environment does not overrule --max-request-mb -----------------------
def test_ray_serve_request_bound_holds_over_the_environment(small_map, monkeypatch):
    """G5: `RAY_SERVE_GRPC_MAX_MESSAGE_SIZE` in the environment silently overruled
    `--max-request-mb` (`os.environ.setdefault`)."""
    pytest.importorskip("ray")
    import ray

    from slamreloc.service import ray_serve

    class Started(Exception):
        pass

    def init(**kwargs):
        raise Started

    monkeypatch.setenv("RAY_SERVE_GRPC_MAX_MESSAGE_SIZE", str(64 << 20))
    monkeypatch.setattr(ray, "is_initialized", lambda: False)
    monkeypatch.setattr(ray, "init", init)
    with pytest.raises(Started):
        ray_serve.deploy({"m": small_map.root}, grpc_port=ray_serve.free_port(),
                         http_port=ray_serve.free_port(), max_request_bytes=1 << 20)
    assert os.environ["RAY_SERVE_GRPC_MAX_MESSAGE_SIZE"] == str(1 << 20)
