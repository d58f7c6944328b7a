"""A ROS 2 bag written from the synthetic scene gives the numbers of the folder it came from:
`map`, `evaluate` (localization) and `slam`, through the CLI."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from slamreloc.datasets import load_dataset
from slamreloc.localize.evaluate import align_to_reference
from slamreloc.map.scene_map import SceneMap
from tests.fuzzing import run_cli, run_cli_output
from tests.rosbag_support import automatic_topics, write_bag  # noqa: F401 - a fixture


def bag_of(scene_dir, sequence: str, path):
    dataset = load_dataset(scene_dir)
    return write_bag(dataset, dataset.frames(sequence), path, version=2, poses="pose")


def _numbers(report: dict, keys) -> dict:
    return {k: report[k] for k in keys}


def test_map_from_a_bag_equals_the_map_from_its_folder(scene_dir, tmp_path):
    bag = bag_of(scene_dir, "seq-01", tmp_path / "map_bag")
    runs = {"folder": [str(scene_dir), "--split", "seq-01"], "bag": [str(bag), "--split", "all"]}
    maps = {}
    for name, args in runs.items():
        status, err = run_cli(["map", *args, "--out", str(tmp_path / name), "--epochs", "2"])
        assert status == 0, err
        maps[name] = json.loads((tmp_path / name / "slamreloc_map.json").read_text())
    # the bag carries poses as quaternions: equal to the folder's matrices up to rounding
    # (1e-16), which shows in the last digits of float statistics, not in counts
    for key in ("n_labelled", "n_keypoints", "n_tracks", "n_depth_labels"):
        assert maps["bag"]["labels"][key] == maps["folder"]["labels"][key], key
    assert maps["bag"]["labels"]["median_reproj_error_px"] == pytest.approx(
        maps["folder"]["labels"]["median_reproj_error_px"], rel=1e-9)
    assert maps["bag"]["camera"] == maps["folder"]["camera"]
    # the labelled database the regressor learns from: the same keypoints, descriptors and
    # world points (the trained weights are not compared: the regressor's k-means centres
    # move when a label moves by 1e-13 m)
    folder_db, bag_db = (SceneMap.load(tmp_path / n).database for n in ("folder", "bag"))
    np.testing.assert_array_equal(bag_db.keypoints, folder_db.keypoints)
    np.testing.assert_array_equal(bag_db.descriptors, folder_db.descriptors)
    np.testing.assert_allclose(bag_db.points, folder_db.points, rtol=0, atol=1e-6)


def test_evaluate_and_slam_on_a_bag_equal_its_folder(scene_dir, kidnap_scene, small_map,
                                                     tmp_path):
    reports = {}
    for scene, seq, command in ((scene_dir, "seq-02", "evaluate"),
                                (kidnap_scene, "seq-03", "slam")):  # 120 frames, 2 kidnaps
        bag = bag_of(scene, seq, tmp_path / f"{seq}_bag")
        for name, data, split in (("folder", scene, seq), ("bag", bag, "all")):
            report = tmp_path / f"{command}_{name}.json"
            args = ([command, str(small_map.root), str(data)] if command == "evaluate" else
                    [command, str(data), "--map", str(small_map.root), "--kidnap-every", "30",
                     "--kidnap-skip", "10"])
            status, err = run_cli([*args, "--split", split, "--report", str(report)])
            assert status == 0, err
            reports[command, name] = json.loads(report.read_text())
    ev_f, ev_b = reports["evaluate", "folder"], reports["evaluate", "bag"]
    assert ev_f["recall"] == ev_b["recall"] and ev_f["n_localized"] == ev_b["n_localized"]
    assert [q["num_inliers"] for q in ev_f["per_query"]] == [q["num_inliers"]
                                                            for q in ev_b["per_query"]]
    for key in ("translation_error_m", "rotation_error_deg"):  # truth: quaternion rounding
        assert [q[key] for q in ev_b["per_query"]] == pytest.approx(
            [q[key] for q in ev_f["per_query"]], rel=1e-6, abs=1e-9)
    counts = ("n_frames", "n_kidnaps", "n_recovered", "n_loop_closures",
              "n_loop_closures_rejected")
    assert _numbers(reports["slam", "bag"], counts) == _numbers(reports["slam", "folder"],
                                                                counts)
    # open3d's RGB-D odometry sums over threads in no fixed order: two runs of the same
    # folder already differ by ~0.1 mm in ATE (the reports round to 0.1 mm)
    for key in ("ate_rmse_m", "ate_rmse_odometry_only_m"):
        assert reports["slam", "bag"][key] == pytest.approx(reports["slam", "folder"][key],
                                                            abs=1e-3)
    assert reports["slam", "bag"]["n_recovered"] >= 1  # the comparison covers a recovery


def test_localize_a_bag_like_its_images(scene_dir, small_map, tmp_path):
    frames = load_dataset(scene_dir).frames("seq-02")
    bag = bag_of(scene_dir, "seq-02", tmp_path / "q_bag")
    outputs = {}
    for name, inputs in (("bag", [str(bag)]), ("folder", [str(f.image_path) for f in frames])):
        status, out, err = run_cli_output(["localize", str(small_map.root), *inputs])
        assert status == 0, err
        outputs[name] = [line.split()[1:] for line in out.splitlines()]  # poses and inliers
    assert len(outputs["bag"]) == len(frames) and outputs["bag"] == outputs["folder"]


def test_sfm_from_a_bag_without_poses(scene_dir, tmp_path):
    dataset = load_dataset(scene_dir)
    bag = write_bag(dataset, dataset.frames("seq-01"), tmp_path / "run", version=2, poses=None)
    status, err = run_cli(["sfm", str(bag), "--out", str(tmp_path / "ds"), "--scale-from-depth"],
                          hang_s=300.0)  # the guard against a hang: SfM takes ~40 s
    assert status == 0, err
    summary = json.loads((tmp_path / "ds" / "sfm.json").read_text())
    assert summary["input_kind"] == "dataset" and summary["metric"]
    assert summary["n_registered"] >= 54
    # frame i of the bag ("run/00000i.png") is the folder's frame i: metres, as the truth
    truth = {f"{i:06d}": f.world_from_cam for i, f in enumerate(dataset.frames("seq-01"))}
    sfm = {Path(f.name).stem: f.world_from_cam for f in load_dataset(tmp_path / "ds").frames()}
    _, record = align_to_reference(sfm, truth)
    assert abs(record["scale"] - 1) < 0.02 and record["median_residual_m"] < 0.02, record
