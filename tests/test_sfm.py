"""`slamreloc sfm`: poses for unposed images, videos and datasets (pycolmap), the metric scale,
and the one-line errors; the written dataset maps."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from slamreloc.datasets import load_dataset
from slamreloc.localize.evaluate import align_to_reference
from slamreloc.io.images import read_image
from tests.fuzzing import run_cli


@pytest.fixture(scope="module")
def photos(scene_dir, tmp_path_factory) -> Path:
    """A plain folder of 40 photos (the map sequence's first images, nothing else)."""
    out = tmp_path_factory.mktemp("photos") / "photos"
    out.mkdir()
    for frame in load_dataset(scene_dir).frames("seq-01")[:40]:
        shutil.copyfile(frame.image_path, out / f"{frame.name.split('/')[-1]}.png")
    return out


def _sfm(args: list[str]) -> tuple[int, str]:
    # the guard against a hang, not a time limit: SfM of 60 images takes ~40 s on 2 cores
    return run_cli(["sfm", *args], hang_s=300.0)


def test_folder_of_photos_gives_a_dataset_that_maps(photos, tmp_path):
    out = tmp_path / "ds"
    status, err = _sfm([str(photos), "--out", str(out)])
    assert status == 0, err
    summary = json.loads((out / "sfm.json").read_text())
    assert summary["matching"] == "exhaustive"  # a small unordered set
    assert summary["n_registered"] >= 38 and summary["n_images"] == 40
    assert len(summary["unregistered"]) == 40 - summary["n_registered"]
    assert summary["mean_reprojection_error_px"] < 1.0 and summary["n_points"] > 2000
    assert summary["metric"] is False and summary["camera"].startswith("SIMPLE_RADIAL")
    focal = float(summary["camera"].split()[3])  # self-calibrated: the truth is 262.5 px
    assert abs(focal / 262.5 - 1) < 0.03, summary["camera"]
    dataset = load_dataset(out)
    assert not dataset.metric and len(dataset.frames("all")) == summary["n_registered"]
    status, err = run_cli(["map", str(out), "--out", str(tmp_path / "map"), "--epochs", "2"])
    assert status == 0, err
    meta = json.loads((tmp_path / "map" / "slamreloc_map.json").read_text())
    assert meta["dataset"]["metric"] is False and meta["camera"]["model"] == "SIMPLE_RADIAL"


def test_dataset_input_is_scaled_to_metres_by_its_depth(scene_dir, tmp_path):
    out = tmp_path / "ds"
    status, err = _sfm([str(scene_dir), "--split", "seq-01", "--out", str(out),
                        "--scale-from-depth"])
    assert status == 0, err
    summary = json.loads((out / "sfm.json").read_text())
    assert summary["metric"] and summary["intrinsics_fixed"]
    truth = {f.name: f.world_from_cam for f in load_dataset(scene_dir).frames("seq-01")}
    sfm = {f.name.rsplit(".", 1)[0]: f.world_from_cam for f in load_dataset(out).frames("all")}
    assert len(sfm) >= 0.9 * len(truth)
    _, record = align_to_reference(sfm, truth)
    assert abs(record["scale"] - 1) < 0.02, record  # metres already: no scale left to fit
    # the SfM poses themselves: within 2 cm / 0.5 deg of the truth (320x240 images)
    assert record["median_residual_m"] < 0.02 and record["median_residual_deg"] < 0.5, record


def test_video_is_sampled_and_reconstructed(scene_dir, tmp_path):
    frames = load_dataset(scene_dir).frames("seq-01")  # 60 frames: 6 s at 10 fps
    video = tmp_path / "walk.mp4"
    h, w = frames[0].camera.height, frames[0].camera.width
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"mp4v"), 10.0, (w, h))
    for f in frames:
        writer.write(read_image(f.image_path)[:, :, ::-1])
    writer.release()
    out = tmp_path / "ds"
    status, err = _sfm([str(video), "--out", str(out), "--fps", "5"])
    assert status == 0, err
    summary = json.loads((out / "sfm.json").read_text())
    assert summary["input_kind"] == "video" and summary["matching"] == "sequential"
    assert summary["n_images"] == len(frames) // 2  # 10 fps sampled at 5
    assert summary["n_registered"] >= 0.8 * summary["n_images"]
    assert sorted(p.name for p in (out / "images" / "walk").iterdir())[0] == "frame-000000.jpg"
    # the same video again, on one OpenMP thread (what a server in the same process leaves
    # behind): the same matches, so the same images registered (COLMAP's faiss-based matcher
    # once registered 21 images here instead of 29) and the same points, up to the few that
    # multi-threaded bundle adjustment's float rounding can move across a filter threshold
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        status, err = _sfm([str(video), "--out", str(tmp_path / "again"), "--fps", "5"])
    finally:
        torch.set_num_threads(threads)
    assert status == 0, err
    again = json.loads((tmp_path / "again" / "sfm.json").read_text())
    assert summary["exact_matching"] and again["unregistered"] == summary["unregistered"]
    assert abs(again["n_points"] - summary["n_points"]) <= 0.002 * summary["n_points"]


def _one_line_error(args, *expected, after_work: bool = False):
    """Exit 2 and one `error:` line naming the problem; nothing else on stderr unless the
    error comes after work that showed its progress (`after_work`)."""
    status, err = _sfm(args)
    lines = err.splitlines()
    assert status == 2 and lines[-1].startswith("error: "), err
    assert len(lines) == 1 or after_work and sum("error" in ln for ln in lines) == 1, err
    for text in expected:
        assert text in lines[-1], err


def test_bad_inputs_are_one_line_errors(photos, scene_dir, tmp_path):
    junk = tmp_path / "broken.mp4"
    junk.write_bytes(b"\x00\x00\x00\x18ftypmp42" + bytes(range(256)) * 40)
    _one_line_error([str(junk), "--out", str(tmp_path / "a")], str(junk), "video")
    noise = tmp_path / "noise"
    noise.mkdir()
    rng = np.random.default_rng(0)
    for i in range(6):
        cv2.imwrite(str(noise / f"{i}.png"), rng.integers(0, 255, (120, 160, 3), np.uint8))
    _one_line_error([str(noise), "--out", str(tmp_path / "b")], str(noise), "of 6 images",
                    "try --matching exhaustive", after_work=True)
    assert not (tmp_path / "b").exists()  # nothing half written
    _one_line_error([str(photos), "--out", str(tmp_path / "c"), "--scale-from-depth"],
                    "--scale-from-depth needs depth")
    _one_line_error([str(scene_dir), "--out", str(tmp_path / "c"), "--scale", "-1"],
                    "--scale must be a positive number")
    _one_line_error([str(photos), "--out", str(tmp_path / "d"), "--camera", "OPENCV 320 240 1"],
                    "--camera: OPENCV takes 8 parameters")
    _one_line_error([str(photos), "--out", str(photos / "inside")], "--out")
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "x").write_text("keep")
    _one_line_error([str(photos), "--out", str(tmp_path / "full")], "not empty")
    assert (tmp_path / "full" / "x").read_text() == "keep"
    _one_line_error([str(tmp_path / "nothing"), "--out", str(tmp_path / "e")], "not found")
