"""Read everything the viewer shows, before any server starts: the map (map_view.py), the
trajectories (trajectories.py), the reports (reports.py, slam_report.py), and the dataset with
the images (images.py). Bad input ends as an InputError naming the file (the CLI prints it as
one line)."""

from __future__ import annotations

from pathlib import Path

from slamreloc.datasets.rosbag import is_rosbag
from slamreloc.errors import InputError
from slamreloc.io.fileio import check_folder
from slamreloc.map.export import check_dataset_of_map
from slamreloc.map.scene_map import SceneMap
from slamreloc.viewer.data import SceneData, ViewerInputs
from slamreloc.viewer.images import open_dataset
from slamreloc.viewer.map_view import load_map
from slamreloc.io.jsonio import report_kind
from slamreloc.viewer.reports import (read_evaluate, read_json, read_pseudo_label,
                                      recorded_dataset)
from slamreloc.viewer.slam_report import read_slam_report
from slamreloc.viewer.trajectories import (attach_truth, read_trajectory, truth_by_stamp,
                                           truth_trajectory)


def load_scene_data(inputs: ViewerInputs) -> SceneData:
    """Read every input; InputError on the first bad one."""
    reports = [(Path(p), read_json(p)) for p in inputs.reports]
    # one with no poses is one of none (a session that never anchored writes one), as in a
    # report's
    trajectories = [read_trajectory(p, allow_empty=True) for p in inputs.trajectories]
    if inputs.dataset is not None and not is_rosbag(Path(inputs.dataset)):  # a bag: a file
        check_folder(Path(inputs.dataset), "dataset")  # (ROS 1), read as every command does
    reference = None
    if inputs.poses is not None:
        from slamreloc.datasets import apply_poses, read_reference

        reference = read_reference(inputs.poses)
    scene_map = SceneMap.load(inputs.map_dir, regressor=False)
    if inputs.dataset is not None:  # the user's: read as every command reads one, its images
        from slamreloc.datasets import load_dataset  # shown as the map's

        dataset = load_dataset(inputs.dataset)
        check_dataset_of_map(scene_map, Path(inputs.dataset), dataset)
    else:  # the one the map records: optional (moved, or never there)
        dataset = open_dataset(scene_map.info.dataset_root)
    if reference is not None:  # the ground truth shown: --poses instead of the dataset's
        if dataset is None:
            raise InputError(f"{inputs.poses}: `poses` needs the dataset its frames belong to "
                             "(`dataset` DATASET; the map records none that can be read)")
        dataset = apply_poses(dataset, reference)
    map_view = load_map(inputs, scene_map, dataset)
    for traj in trajectories:
        attach_truth(traj, dataset)
    truths = [t for t in trajectories if t.kind == "groundtruth"]
    for traj in trajectories:
        if traj.kind == "estimate" and truths and traj.errors_m is None:
            truth_by_stamp(traj, truths[0])
    scene = SceneData(map_view, max_images=inputs.max_images,
                      thumbnail_width=inputs.thumbnail_width)
    for traj in trajectories:
        scene.trajectories.append(traj)
        has_gt = any(t.kind == "groundtruth" for t in trajectories)
        if traj.kind == "estimate" and not has_gt:
            gt = truth_trajectory(traj)
            if gt is not None:
                scene.trajectories.append(gt)
    for path, data in reports:
        kind = report_kind(data)
        if kind == "evaluate":
            recorded = recorded_dataset(path, data)
            ds = (dataset if inputs.dataset or inputs.poses or not recorded
                  else (open_dataset(recorded) or dataset))
            scene.evaluations.append(read_evaluate(path, data, ds, trajectories))
        elif kind == "slam":
            scene.slams.append(read_slam_report(path, data, trajectories))
        elif kind == "pseudo-label":
            scene.pseudo_labels.append(read_pseudo_label(path, data))
        else:  # what else would be shown is not what the user meant to give
            raise InputError(f"`report` {path}: not a report of evaluate, slam or "
                             "pseudo-label (a JSON object without their fields)")
    return scene
