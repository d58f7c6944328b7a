"""What each command does, once: check its inputs, then where its outputs may go, load the map
and the dataset, run the library on the loaded objects, write its report and files.

The library below (`slamreloc.localize`, `slamreloc.slam`, `slamreloc.map`, ...) takes loaded
objects and configs and never names a command-line flag; the messages that do are here.
`slamreloc.cli.commands` declares the flags and calls these; the demo composes them.
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterator
from contextlib import nullcontext
from dataclasses import replace
from pathlib import Path

from rich.table import Table

from slamreloc.datasets import Dataset, load_dataset, read_frame_depth, read_image
from slamreloc.datasets.poses import NAMES_FILE, TUM_FILE, check_names_sidecar_free
from slamreloc.errors import InputError, OutOfMemory
from slamreloc.io.fileio import resolved
from slamreloc.geometry import (
    Rigid3,
    distinct_stamps,
    names_sidecar,
    tum_line,
    write_tum_trajectory,
)
from slamreloc.io.outputs import check_outputs, outputs_together, reads_as, write_json
from slamreloc.io.jsonio import read_json, written_report_kind
from slamreloc.localize.evaluate import (
    EvaluationConfig,
    evaluate_map,
    prepare_reference,
    query_frames,
    write_tum,
)
from slamreloc.localize.plots import PLOT_FILE
from slamreloc.map.format import check_is_map, is_map
from slamreloc.map.lock import map_write_lock
from slamreloc.map.scene_map import SceneMap
from slamreloc.map.surface import IcpConfig, refine_with_depth
from slamreloc.runtime.progress import console, shown
from slamreloc.types import Camera, Frame, camera_problem, lens_camera_problem


def evaluate(map_dir: Path, dataset_dir: Path, report: Path, split: str = "test",
             method: str = "regressor", trajectory: Path | None = None,
             plot: Path | None = None, device: str = "cpu", progress: bool = True,
             depth: bool = False, poses: Path | None = None,
             references: list[Path] | tuple[Path, ...] = (), guided: bool = True) -> dict:
    """`slamreloc evaluate`: localize a split, write REPORT.json (and the estimated poses as a
    TUM `trajectory`, a `plot`); returns the report. `poses`: the dataset's poses from this
    file (`datasets.poses`); `references`: also scored against these, aligned on the map's
    training cameras; `guided`: `EvaluationConfig`. Everything is read and checked before the
    work."""
    check_is_map(map_dir)  # what the inputs are, then where the outputs may go
    if plot is not None and Path(plot).suffix.lower() != ".png":
        raise InputError(f"{plot}: --plot writes a PNG picture: give a path ending in .png")
    check_outputs({"--report": report, "--trajectory": trajectory,
                   "--trajectory's names file": sidecar(trajectory), "--plot": plot},
                  {"the map": map_dir, "the dataset": dataset_dir, "--poses": poses,
                   **{f"--reference {p}": p for p in references}, **recorded_inputs(map_dir)},
                  files={"--report": REPORT_FILE, "--trajectory": TUM_FILE,
                         "--trajectory's names file": NAMES_FILE, "--plot": PLOT_FILE})
    if trajectory is not None:
        check_names_sidecar_free(trajectory, "--trajectory")
    scene_map = SceneMap.load(map_dir)
    labels = reference_labels(list(references))
    dataset = load_dataset(dataset_dir, poses)
    frames = query_frames(dataset, split)
    unposed = next((f for f in frames if f.world_from_cam is None), None)
    if unposed is not None and dataset.poses_source != "dataset":
        raise InputError(f"{dataset.poses_source}: no pose for query frame {unposed.name} "
                         "(--poses gives the queries' ground truth)")
    if unposed is not None:  # named by the dataset, not by a file a bag was unpacked to
        from slamreloc.datasets.rosbag import is_rosbag

        hint = ("give --poses, or --topic pose=TOPIC (a pose topic or tf:PARENT:CHILD)"
                if is_rosbag(Path(dataset_dir)) else "give --poses")
        raise InputError(f"{dataset_dir}: query frame {unposed.name} has no ground-truth pose "
                         f"in the dataset ({hint})")
    scoring = [prepare_reference(Path(p), label, scene_map, dataset, frames)
               for p, label in zip(references, labels)]
    refine = depth_refiner(scene_map, dataset) if depth else None
    config = EvaluationConfig(method=method, device=device, guided=guided, progress=progress)
    result = evaluate_map(scene_map, dataset, split, config, refine, scoring)
    if plot:
        from slamreloc.localize.plots import plot_evaluation
    with outputs_together():  # interrupted: all new, or all as they were
        if plot:
            plot_evaluation(plot, {method: result.results}, result.frames)
        if trajectory:
            write_tum(trajectory, result.results)
        write_json(report, result.report)
    return result.report


def recorded_inputs(map_dir: Path) -> dict[str, Path | None]:
    """What the map at `map_dir` records it was made from (`MapMeta.recorded_inputs`): inputs
    of every command that has the map."""
    from slamreloc.map.meta import MapMeta

    return MapMeta.read(map_dir).recorded_inputs()


def read_report(path: Path) -> dict:
    """A report a command may replace: a report of slamreloc's (`written_report_kind`:
    evaluate, slam, pseudo-label, with every field that command writes; not any JSON object,
    as a dataset's scene.json or a user's notes) that is not a map's own file."""
    if is_map(path.parent):
        raise InputError(f"{path}: a file of the map {path.parent}")
    data = read_json(path, "report")
    if written_report_kind(data) == "other":
        raise InputError(f"{path}: a JSON file that is no slamreloc report")
    return data


# `check_outputs`' `files` entry of a --report
REPORT_FILE = reads_as(read_report, "a slamreloc report (evaluate, slam or pseudo-label) "
                                    "outside any map folder")


def sidecar(trajectory: Path | None) -> Path | None:
    """The frame-names file written beside a TUM trajectory (`names_sidecar`), None for none."""
    return None if trajectory is None else names_sidecar(trajectory)


def depth_refiner(scene_map: SceneMap, dataset: Dataset, config: IcpConfig = IcpConfig()):
    """`(frame, world_from_cam) -> world_from_cam` (map frame from the camera, metres): the
    frame's depth fitted onto the map's surface (`refine_with_depth`), the PnP pose where the
    fit is not accepted."""
    surface = scene_map.surface
    if surface is None:
        raise InputError(f"{scene_map.root}: map has no surface (it was built without depth); "
                         "--depth needs one")

    def refine(frame: Frame, world_from_cam: Rigid3) -> Rigid3:
        depth = read_frame_depth(frame, dataset.depth_units_per_metre)
        return refine_with_depth(surface, depth, frame.camera, frame.depth_camera,
                                 world_from_cam, config).chosen()

    return refine


def reference_labels(paths: list[Path]) -> list[str]:
    """Short distinct labels of the --reference paths: the file name, with as many parent
    folders as tell two apart (and a COLMAP model's `sparse/0` its project folder's name).
    InputError for a path given twice."""
    parts = [resolved(p).parts for p in paths]  # a link loop too
    depth = [1] * len(paths)
    for i, p in enumerate(parts):  # `.../redkitchen/sparse/0` -> `redkitchen/sparse/0`
        while depth[i] < len(p) and (p[-depth[i]].isdigit() or p[-depth[i]] == "sparse"):
            depth[i] += 1
    while True:
        labels = ["/".join(p[-d:]) for p, d in zip(parts, depth)]
        clash = [i for i, label in enumerate(labels) if labels.count(label) > 1]
        if not clash:
            return labels
        if all(depth[i] >= len(parts[i]) for i in clash):
            raise InputError(f"{paths[clash[0]]}: --reference given twice")
        for i in clash:
            depth[i] = min(depth[i] + 1, len(parts[i]))


def localize(map_dir: Path, images: list[Path],
             intrinsics: Camera | tuple[float, float, float, float] | None = None,
             method: str = "regressor", guided: bool = True) -> Iterator[tuple[str, str]]:
    """`slamreloc localize`: yield (line, status) per image (or per frame of a ROS bag among
    `images`, each named as `_query_images` says): a TUM line plus inlier count ("ok"),
    `# name: not localized` ("failed"), or `error: ...` for an image that cannot be read or
    is out of bounds ("error").
    `intrinsics`: a Camera (any lens model, scaled to each image), pinhole (fx, fy, cx, cy)
    in pixels, else the bag's camera or the map's, scaled to each image (`Camera.for_image`:
    an image of another aspect ratio than the camera is an "error" line, never stretched)."""
    if intrinsics is not None and not isinstance(intrinsics, Camera):
        problem = camera_problem(1, 1, *intrinsics)
        if problem:
            raise InputError(f"--intrinsics: {problem}")
    scene_map = SceneMap.load(map_dir)
    localizer = EvaluationConfig(method=method, guided=guided).localizer(scene_map)
    for name, path, own_camera in _query_images(images):
        try:
            # the bounds, the extractor's included, are checked before anything is decoded
            image = read_image(path, fits=localizer.extractor.check_size)
        except InputError as err:
            yield f"error: {err}", "error"
            continue
        h, w = image.shape[:2]
        try:  # a camera of another aspect ratio than the image is never stretched onto it
            if isinstance(intrinsics, Camera):
                camera = intrinsics.for_image(w, h, f"{path}: --camera")
            elif intrinsics:
                problem = lens_camera_problem("PINHOLE", w, h, *intrinsics, ())
                if problem:
                    raise InputError(f"{path}: --intrinsics: {problem}")
                camera = Camera(w, h, *intrinsics)
            elif own_camera is not None:
                camera = own_camera.for_image(w, h, f"{path}: the bag's camera")
            else:
                camera = scene_map.camera.for_image(w, h, f"{path}: the map's camera (give "
                                                    "--camera or --intrinsics)")
        except InputError as err:
            yield f"error: {err}", "error"
            continue
        try:
            est = localizer.localize(image, camera).estimate
        except OutOfMemory as err:  # this image; the next may fit
            yield f"error: {path}: {err}", "error"
            continue
        if est.success:
            yield f"{tum_line(line_name(name), est.world_from_cam)} {est.num_inliers}", "ok"
        else:
            yield f"# {line_name(name)}: not localized ({est.num_inliers} inliers)", "failed"


def line_name(name: str) -> str:
    """An image's name as the first field of an output line: as it is, or, where it holds a
    space, a control character or a `%`, or starts with `#` (it would split the line's
    fields or read as a comment), percent-encoded (`my%20photo.png`; `urllib.parse.unquote`
    gives it back)."""
    from urllib.parse import quote

    if name.startswith("#") or "%" in name or any(c.isspace() or not c.isprintable()
                                                  for c in name):
        try:  # a file name's undecodable bytes (surrogates) as the bytes they were
            raw = name.encode("utf-8", "surrogateescape")
        except UnicodeEncodeError:
            raw = name.encode("utf-8", "backslashreplace")
        return quote(raw, safe="/")
    return name


def _query_images(paths: list[Path]):
    """(name, image file, its camera or None) of each image file, and of each frame of a ROS
    bag among them (named by frame, with the bag's camera). An image file is named by its
    file name, unless another image file of the run has that file name and another path
    (`a/q.png`, `b/q.png`): then by its path as given, so that no two images share a name (one
    image given twice by one path is one image, and keeps its file name)."""
    from slamreloc.datasets.rosbag import is_rosbag, load_rosbag

    bags = [is_rosbag(Path(path)) for path in paths]
    paths_of: dict[str, set[Path]] = {}  # file name -> the image files' paths of that name
    for path, bag in zip(paths, bags):
        if not bag:
            paths_of.setdefault(Path(path).name, set()).add(Path(path))
    for path, bag in zip(paths, bags):
        if bag:
            for frame in load_rosbag(Path(path)).frames("all"):
                yield frame.name, frame.image_path, frame.camera
        else:
            name = Path(path).name
            yield (name if len(paths_of[name]) == 1 else str(path)), path, None


def slam(dataset: Path, map_dir: Path | None, report: Path, split: str = "test",
         kidnap_every: int = 0, kidnap_skip: int = 20, odometry: str = "auto",
         trajectory: Path | None = None, progress: bool = True,
         plugin_options: dict | None = None, plugins: list | None = None,
         poses: Path | None = None, out: Path | None = None, save_every_s: float = 30.0,
         live=None, kidnap_from: int = -1) -> dict:
    """`slamreloc slam`: run the backend, write the report and trajectory, print a table.
    plugin_options: keyword arguments of the relocalization plugin (benchmarks, tests);
    plugins: the backend's plugins instead of that one (benchmarks: a test-harness plugin);
    poses: the ground truth from this pose file instead of the dataset's; out: learn a map
    while tracking and write it there (from nothing without `map_dir`, else extending it);
    live: its `LiveMapConfig`; kidnap_from: processed frames before the first kidnapping
    (-1: `kidnap_every`)."""
    from slamreloc.slam.poses import final_trajectory
    from slamreloc.slam.run import TOPIC_PREFIX, SlamRunConfig, run_slam

    if kidnap_every < 0 or kidnap_skip < 0:
        raise InputError("--kidnap-every and --kidnap-skip must be >= 0")
    if kidnap_from < -1:
        raise InputError(f"--kidnap-from must be >= 0, got {kidnap_from}")
    if not math.isfinite(save_every_s) or save_every_s < 0:
        raise InputError(f"--save-every must be a number of seconds >= 0, got {save_every_s}")
    if map_dir is None and out is None:
        raise InputError("--map or --out is needed: a map to relocalize in, or one to learn")
    if map_dir is not None:
        check_is_map(map_dir)  # what the inputs are, then where the outputs may go
    odometry_file = (odometry if odometry not in ("auto", "kiss-icp", "open3d")
                     and not odometry.startswith(TOPIC_PREFIX) else None)
    check_outputs({"--report": report, "--trajectory": trajectory,
                   "--trajectory's names file": sidecar(trajectory), "--out": out},
                  {"the dataset": dataset, "the map": map_dir, "--odometry": odometry_file,
                   "--poses": poses, **(recorded_inputs(map_dir) if map_dir else {})},
                  folders={"--out": (is_map, "a slamreloc map")},
                  files={"--report": REPORT_FILE, "--trajectory": TUM_FILE,
                         "--trajectory's names file": NAMES_FILE})
    if trajectory is not None:
        check_names_sidecar_free(trajectory, "--trajectory")
    config = SlamRunConfig(split=split, odometry=odometry, kidnap_every=kidnap_every,
                           kidnap_skip=kidnap_skip, progress=progress,
                           kidnap_from=kidnap_every if kidnap_from < 0 else kidnap_from,
                           plugin_options=plugin_options or {}, poses=poses,
                           save_every_s=save_every_s)
    if live is not None:
        config = replace(config, live=live)
    # the learned map's write lock for the whole session (as `map --out` holds it): another
    # command writing that map fails at once, not after this session replaced its work. The
    # final map, the trajectory and the report are put in place together (the periodic saves
    # during the session land at once: `LiveMappingPlugin.save`)
    with map_write_lock(out) if out is not None else nullcontext(), outputs_together():
        result, backend, frames = run_slam(dataset, map_dir, config, plugins, out)
        if trajectory is not None:
            world_from_cam = final_trajectory(backend)
            keep = [i for i, p in enumerate(world_from_cam) if p is not None]
            stamps = distinct_stamps([f.timestamp for f in frames])  # sequences: indices
            write_tum_trajectory(
                trajectory, [stamps[i] for i in keep], [world_from_cam[i] for i in keep],
                [f"slamreloc slam {dataset} (split {split}), map frame, camera-to-world",
                 "timestamp tx ty tz qx qy qz qw"], names=[frames[i].name for i in keep])
            result["trajectory"] = os.path.relpath(trajectory, Path(report).parent)
        write_json(report, result)
    print_slam_summary(result)
    return result


def pseudo_label(map_dir: Path, dataset_dir: Path, out: Path, report: Path,
                 split: str | None = None, config=None, truth: Path | None = None,
                 poses: Path | None = None, progress: bool = True) -> tuple[SceneMap, dict]:
    """`slamreloc pseudo-label`: register DATASET's split in MAP, write NEW_MAP at `out` and
    REPORT.json; returns (the new map, the report). The report is scored against `truth`'s
    poses (a dataset of the same frames), else DATASET's, with `poses` (a pose file,
    `datasets.poses`) in place of whichever is used. `config`: a `PseudoLabelConfig`."""
    from slamreloc.pseudo_label import PseudoLabelConfig, update_map

    check_is_map(map_dir)  # what the inputs are, then where the outputs may go
    check_outputs({"--report": report, "--out": out},
                  {"the map": map_dir, "the dataset": dataset_dir, "--truth": truth,
                   "--poses": poses, **recorded_inputs(map_dir)},
                  folders={"--out": (is_map, "a slamreloc map")},
                  files={"--report": REPORT_FILE})
    old = SceneMap.load(map_dir)
    dataset = load_dataset(dataset_dir)
    new_map, result = update_map(old, dataset, out, split, config or PseudoLabelConfig(),
                                 scoring_truth(dataset, truth, poses), progress, report)
    prec = result.get("pseudo_label_precision_10cm")
    console.print(
        f"[green]map written[/green] to {shown(new_map.root)}: {result['n_frames_registered']}/"
        f"{result['n_frames']} frames registered, {result['n_pseudo_labels']} pseudo-labels "
        f"({result['n_new_points']} new points)"
        + ("" if prec is None else f", precision {100 * prec:.1f} % within 10 cm, median pose "
           f"error {100 * result['median_pose_error_m']:.1f} cm / "
           f"{result['median_pose_error_deg']:.2f} deg"))
    return new_map, result


def scoring_truth(dataset: Dataset, truth: Path | None, poses: Path | None) -> Dataset | None:
    """The dataset whose poses score a pseudo-label report: `truth` (a dataset of the same
    frames) with `poses` (a pose file) in place of its own if given, else `dataset` with
    `poses`'; None: `dataset`'s own poses."""
    from slamreloc.datasets import apply_poses, read_reference

    if truth is not None:
        return load_dataset(truth, poses)
    return None if poses is None else apply_poses(dataset, read_reference(poses))


def print_slam_summary(r: dict) -> None:
    table = Table(title="SLAM backend")
    for col in ("frames", "ATE", "ATE odometry only", "kidnaps recovered", "frames to recover",
                "loop closures (rejected)", "backend fps"):
        table.add_column(col)
    cm = (lambda v: "-" if v is None else f"{100 * v:.1f} cm")  # noqa: E731
    table.add_row(str(r["n_frames"]), cm(r["ate_rmse_m"]), cm(r["ate_rmse_odometry_only_m"]),
                  f"{r['n_recovered']}/{r['n_kidnaps']}",
                  "-" if r["median_frames_to_recover"] is None
                  else f"{r['median_frames_to_recover']:.0f}",
                  f"{r['n_loop_closures']} ({r['n_loop_closures_rejected']})",
                  "-" if r["backend_fps"] is None else f"{r['backend_fps']:.1f}")
    console.print(table)
    live = r.get("live_map")
    if live:
        console.print(f"map learned: {live['n_keyframes']} keyframes, {live['n_rows']} rows, "
                      f"{len(live['rounds'])} training rounds (learner busy "
                      f"{live['learner_share'] or 0:.1f}x the tracking time, on its own "
                      "thread); written "
                      f"to {shown(live['out'])}")
