"""The `slamreloc` commands. Each imports the pipeline it runs only when it runs; the choices
of its options come from the registries (`slamreloc.cli.choices`)."""

from __future__ import annotations

import os
import re
import sys
from dataclasses import replace
from functools import cache
from pathlib import Path
from typing import Annotated, Optional

import typer

from slamreloc.cli.choices import (
    Arch,
    Device,
    FeatureName,
    Mapper,
    Matching,
    Method,
    Precision,
    Update,
)
from slamreloc.cli.serve import serve
from slamreloc.errors import InputError, terminal_line
from slamreloc.io.outputs import naming_output

POSES_HELP = ("take the frames' poses from this file instead of the dataset's: a COLMAP model "
              "folder, 'name tx ty tz qx qy qz qw' lines, a TUM file or another dataset "
              "folder (docs/formats.md)")
GUIDED_HELP = ("regressor (on by default): refine the pose on the map's database points "
               "matched near it, on maps whose labels agree with their images "
               "(docs/method.md); --no-guided: the pose from the regressed points alone")
SPLIT_HELP = ("train | test | all | a role (kidnap, ...) | a sequence, or a comma-separated list "
              "of them, each sequence once")
# upper bounds of counts the options take: beyond them a value is a typo, not a wish (1e11
# epochs would train for ever, silently: a run's progress is shown per epoch)
MAX_EPOCHS = 100_000
MAX_AUGMENT_VIEWS = 16  # simulated views per mapping image: each adds about a third of the rows
MAX_ROUNDS = 1000
MAX_FRAMES = 10_000_000  # a count of frames an option gives (a day of video at 100 Hz: 8.6M)


def check_range(flag: str, value: int | float | None, low: int | float,
                high: int | float) -> None:
    """InputError `FLAG must be in LOW..HIGH, got VALUE` unless `value` (None: not given) is
    within [low, high]."""
    if value is not None and not low <= value <= high:
        raise InputError(f"{flag} must be in {low}..{high}, got {str(value)[:24]}")


def guided_choice(method: Method, guided: bool | None) -> bool:
    """`--guided` / `--no-guided` as given (None: not given, which is guided): an InputError
    with `--method matching`, which has no guided step to switch."""
    if guided is not None and method != Method.regressor:
        flag = "--guided" if guided else "--no-guided"
        raise InputError(f"{flag} is for --method regressor; --method {method.value} has no "
                         "guided step (leave it out)")
    return True if guided is None else guided


app = typer.Typer(add_completion=False, no_args_is_help=True, pretty_exceptions_enable=False,
                  help="Camera relocalization with a lightweight scene-coordinate regressor.")
app.command()(serve)


# commands that never read a dataset (localize reads a ROS bag given as its images)
NO_DATASET_COMMANDS = ("demo", "serve")


@app.callback()
def options(
    ctx: typer.Context,
    limit: Annotated[Optional[list[str]], typer.Option(
        "--limit", metavar="NAME=VALUE",
        help="change a bound on untrusted input, before the command: max_image_pixels, "
             "max_feature_bytes, max_image_bytes, max_json_bytes, ... (docs/formats.md, "
             "'Input bounds'; also SLAMRELOC_<NAME> variables)")] = None,
    topic: Annotated[Optional[list[str]], typer.Option(
        "--topic", metavar="KIND=NAME",
        help="a ROS bag dataset's topic instead of the one found automatically: image=, "
             "depth=, camera_info=, pose= (a pose topic or tf:PARENT:CHILD); repeatable "
             "(docs/formats.md, 'ROS bags')")] = None,
) -> None:
    """Camera relocalization with a lightweight scene-coordinate regressor."""
    from slamreloc.io.limits import check_environment, limits, parse_limits, set_limits

    # before any command: a SLAMRELOC_ variable misspelt (or a bound's value that is no
    # number) ends it in one line, rather than being ignored or found at the first input
    check_environment()
    limits()
    if limit:
        set_limits(**parse_limits(limit))
    from slamreloc.datasets.rosbag import parse_topics, set_topics

    set_topics(parse_topics(topic or []))  # none: found in each bag (never an earlier run's)
    if topic and ctx.invoked_subcommand in NO_DATASET_COMMANDS:
        raise InputError(f"`topic` chooses a ROS bag DATASET's topics, and "
                         f"'{ctx.invoked_subcommand}' reads no dataset")


@app.command("map")
def map_cmd(
    dataset: Annotated[Path, typer.Argument(
        metavar="DATASET",
        help="dataset (7-Scenes, TUM, synthetic, COLMAP, `slamreloc sfm` output, a ROS bag)")],
    out: Annotated[Path, typer.Option("--out", help="map folder to write")],
    split: Annotated[str, typer.Option(help=SPLIT_HELP)] = "train",
    features: Annotated[FeatureName, typer.Option(help="local features")] = FeatureName.sift,
    superpoint_weights: Annotated[Optional[Path], typer.Option(
        help="SuperPoint weights (.pth), needed with --features superpoint")] = None,
    arch: Annotated[Optional[Arch], typer.Option(
        help="regressor: wide (1.4 M, the default), paper (2.3 M), tiny (0.7 M)")] = None,
    epochs: Annotated[Optional[int], typer.Option(help="training epochs")] = None,
    device: Annotated[Device, typer.Option(help="training device")] = Device.auto,
    precision: Annotated[Precision, typer.Option(
        help="training precision: auto = bf16 where the hardware runs it natively (AMX, "
             "AVX512-BF16, recent CUDA), else fp32")] = Precision.auto,
    resume: Annotated[bool, typer.Option(
        "--resume", help="continue an interrupted run from its training checkpoint")] = False,
    poses: Annotated[Optional[Path], typer.Option(metavar="FILE", help=POSES_HELP)] = None,
    augment_views: Annotated[Optional[int], typer.Option(
        help="simulated views per mapping image (affine warps: tilt, rotation, zoom) whose "
             "features also train the regressor: steadier on viewpoints the mapping images "
             "lack, at about twice the training time with 3; default 0 (none)")] = None,
) -> None:
    """Extract features, build scene-coordinate labels and train the regressor into OUT."""
    from slamreloc.datasets import load_dataset
    from slamreloc.map.build import MapConfig, build_map

    check_range("--epochs", epochs, 1, MAX_EPOCHS)
    check_range("--augment-views", augment_views, 0, MAX_AUGMENT_VIEWS)
    config = MapConfig(features=features.value, device=device.value)
    if augment_views:
        config.augment = replace(config.augment, views=augment_views)
    if arch is not None:
        config.arch = arch.value
    if features == FeatureName.superpoint:
        if superpoint_weights is None or not str(superpoint_weights).strip():
            raise InputError("--features superpoint needs --superpoint-weights FILE (the .pth "
                             "of SuperPoint; nothing is downloaded)")
        config.feature_options = {"weights": str(superpoint_weights)}
    elif superpoint_weights is not None:
        raise InputError("--superpoint-weights is for --features superpoint; these features "
                         f"are {features.value}")
    config.train = replace(config.train, precision=precision.value,
                           **({} if epochs is None else {"epochs": epochs}))
    scene_map = build_map(load_dataset(dataset, poses), out, split, config, resume=resume)
    _print_map(scene_map)


@app.command()
def evaluate(
    map_dir: Annotated[Path, typer.Argument(metavar="MAP", help="map folder")],
    dataset: Annotated[Path, typer.Argument(
        metavar="DATASET", help="dataset folder with ground-truth poses")],
    report: Annotated[Path, typer.Option("--report", help="REPORT.json to write")],
    split: Annotated[str, typer.Option(help=SPLIT_HELP)] = "test",
    method: Annotated[Method, typer.Option(help="regressor, or the matching baseline")] =
    Method.regressor,
    trajectory: Annotated[Optional[Path], typer.Option(
        help="write the estimated poses (TUM, camera-to-world; frame names in "
             "<stem>.names.txt)")] = None,
    plot: Annotated[Optional[Path], typer.Option(help="write error curves and top view (PNG)")] =
    None,
    device: Annotated[Device, typer.Option(
        help="regressor device; cpu by default, where localize, slam and serve run it, so the "
             "report's poses and timings are theirs (auto would take CUDA when present, "
             "and bf16 there)")] = Device.cpu,
    depth: Annotated[bool, typer.Option(
        "--depth", help="refine each pose by ICP of the frame's depth against the map's "
        "surface (RGB-D relocalization)")] = False,
    poses: Annotated[Optional[Path], typer.Option(
        metavar="FILE", help=POSES_HELP + "; the ground truth scored against")] = None,
    reference: Annotated[Optional[list[Path]], typer.Option(
        metavar="FILE", help="also score against this reference (read as --poses is), moved "
        "into the map's frame by a similarity fitted on the map's training cameras only; "
        "repeatable")] = None,
    guided: Annotated[Optional[bool], typer.Option(help=GUIDED_HELP)] = None,
) -> None:
    """Localize every frame of a split against MAP and score it against ground truth."""
    from slamreloc.cli import jobs

    summary = jobs.evaluate(map_dir, dataset, report, split, method.value, trajectory, plot,
                            device.value, depth=depth, poses=poses,
                            references=list(reference or []),
                            guided=guided_choice(method, guided))
    from slamreloc.localize.evaluate import print_summary

    print_summary([summary])


@app.command()
def localize(
    map_dir: Annotated[Path, typer.Argument(metavar="MAP", help="map folder")],
    images: Annotated[list[Path], typer.Argument(
        metavar="IMAGE", help="image files, or ROS bags (each frame, with the bag's camera)")],
    intrinsics: Annotated[Optional[tuple[float, float, float, float]], typer.Option(
        metavar="FX FY CX CY",
        help="four numbers in pixels, pinhole (default: the map's camera, scaled to the "
             "image)")]
    = None,
    camera: Annotated[Optional[str], typer.Option(
        help="a COLMAP camera string, any lens model: \"OPENCV 640 480 fx fy cx cy k1 k2 p1 "
             "p2\" (as in cameras.txt; scaled to an image of another size); for a ROS bag "
             "without a calibrated CameraInfo, its camera")] = None,
    method: Annotated[Method, typer.Option()] = Method.regressor,
    guided: Annotated[Optional[bool], typer.Option(help=GUIDED_HELP)] = None,
) -> None:
    """Print `name tx ty tz qx qy qz qw inliers` (camera-to-world) for each image."""
    from slamreloc.cli import jobs

    if camera is not None and intrinsics is not None:
        raise InputError("--camera and --intrinsics: give one of them")
    from slamreloc.datasets.rosbag import default_topics_unread, is_rosbag

    if default_topics_unread() and not any(is_rosbag(p) for p in images):  # before the work
        raise InputError("`topic` chooses a ROS bag DATASET's topics, and 'localize' reads no "
                         "bag here (its IMAGEs are image files)")
    if camera is not None:
        from slamreloc.types import Camera

        query_camera = Camera.parse(camera, "--camera")
    else:
        query_camera = intrinsics
    if sys.stdout is None:  # started with its standard output closed (`>&-`)
        raise InputError("standard output is closed: the poses would be lost (send them to "
                         "a file or a pipe)")
    from slamreloc.datasets.rosbag import camera_in_place_of_info

    errors = 0
    stand_in = query_camera if camera is not None else None  # for a bag without CameraInfo
    with camera_in_place_of_info(stand_in):
        for line, status in jobs.localize(map_dir, images, query_camera, method.value,
                                           guided_choice(method, guided)):
            if status == "error":
                errors += 1
                typer.echo(terminal_line(with_flags(line)), err=True)  # a name's ESC or break
                continue
            try:
                with naming_output("standard output"):  # a full disk, a closed pipe: said so
                    typer.echo(line)
                    sys.stdout.flush()
            except BrokenPipeError:  # (click would end quietly with status 1)
                sys.stdout = open(os.devnull, "w")  # nothing more goes to the closed pipe
                raise InputError("standard output: the pipe's reader has closed it; the poses "
                                 "that follow would be lost") from None
    if errors:
        raise typer.Exit(2)


@app.command("pseudo-label")
def pseudo_label_cmd(
    map_dir: Annotated[Path, typer.Argument(metavar="MAP", help="map folder to update")],
    dataset: Annotated[Path, typer.Argument(
        metavar="DATASET", help="dataset with the unlabelled sequence")],
    out: Annotated[Path, typer.Option("--out", help="NEW_MAP folder to write (MAP is kept)")],
    report: Annotated[Path, typer.Option("--report", help="REPORT.json to write")],
    split: Annotated[Optional[str], typer.Option(
        help="sequences to use (default: the 'unlabelled' role, else all)")] = None,
    rounds: Annotated[int, typer.Option(help="registration + map-extension rounds")] = 8,
    update: Annotated[Update, typer.Option(
        help="finetune: from the map's weights (fast); retrain: from scratch")] =
    Update.finetune,
    epochs: Annotated[Optional[int], typer.Option(
        help="update epochs (default: a quarter of the map's for finetune, all for retrain)")] =
    None,
    truth: Annotated[Optional[Path], typer.Option(
        help="dataset with the true poses of the same frames, only to score the report")] =
    None,
    device: Annotated[Device, typer.Option(help="training device")] = Device.auto,
    poses: Annotated[Optional[Path], typer.Option(
        metavar="FILE", help="score the report against this pose file's poses (read as "
        "`map --poses` reads it), matched to --truth's frames if given, else DATASET's")] =
    None,
) -> None:
    """Register an unlabelled sequence in MAP, pseudo-label and extend it, update the regressor.

    DATASET's poses are never read except to score the report (as are --truth's and
    --poses')."""
    from slamreloc.cli import jobs
    from slamreloc.pseudo_label import PseudoLabelConfig

    check_range("--rounds", rounds, 1, MAX_ROUNDS)
    check_range("--epochs", epochs, 1, MAX_EPOCHS)
    config = PseudoLabelConfig(rounds=rounds, update=update.value, epochs=epochs,
                               device=device.value)
    jobs.pseudo_label(map_dir, dataset, out, report, split, config, truth, poses)


@app.command()
def sfm(
    source: Annotated[Path, typer.Argument(
        metavar="INPUT", help="a folder of images, a video file, or a dataset (its poses are "
                              "ignored)")],
    out: Annotated[Path, typer.Option("--out", help="DATASET folder to write (COLMAP model)")],
    camera: Annotated[str, typer.Option(
        help="a COLMAP model (SIMPLE_RADIAL, OPENCV, OPENCV_FISHEYE, ...; intrinsics "
             "estimated) or a camera string \"OPENCV 640 480 fx fy cx cy k1 k2 p1 p2\" "
             "(starting intrinsics); default: the dataset's camera, else SIMPLE_RADIAL; "
             "needed for a ROS bag without a calibrated CameraInfo")] = "",
    fix_intrinsics: Annotated[bool, typer.Option(
        "--fix-intrinsics", help="keep the --camera string's intrinsics fixed")] = False,
    matching: Annotated[Matching, typer.Option(
        help="auto: exhaustive up to 60 unordered images, else sequential")] = Matching.auto,
    mapper: Annotated[Mapper, typer.Option(
        help="global (GLOMAP: fast) or incremental (COLMAP's: slower on long sequences, "
             "more robust on small sets and unknown intrinsics); auto: global for 100+ "
             "images with a known camera, else incremental")] = Mapper.auto,
    fps: Annotated[Optional[float], typer.Option(
        help="video: frames sampled per second [default: 2]")] = None,
    split: Annotated[str, typer.Option(help="dataset input: which frames")] = "all",
    overlap: Annotated[Optional[int], typer.Option(
        help="sequential matching: next N images [default: 10]")] = None,
    max_features: Annotated[int, typer.Option(help="SIFT features per image")] = 4096,
    scale_from_depth: Annotated[bool, typer.Option(
        "--scale-from-depth", help="metric scale from the input's depth")] = False,
    scale: Annotated[Optional[float], typer.Option(
        help="metric scale: metres per SfM unit")] = None,
    min_registered: Annotated[float, typer.Option(
        help="fail when fewer than this share of the images register")] = 0.5,
    select: Annotated[str, typer.Option(
        metavar="auto|all|parallax",
        help="which frames or photos SfM uses: parallax keeps one once its tracked points "
             "reach --min-parallax to the last one kept (near-duplicates of a slow camera "
             "make SfM fail); all keeps every one; auto: parallax for a video (among the "
             "--fps samples), all for photos and datasets")] = "auto",
    min_parallax: Annotated[Optional[float], typer.Option(
        metavar="DEG", help="--select parallax: median triangulation angle, degrees "
        "[default: 0.75]")] = None,
) -> None:
    """Poses for unposed images or a video: SfM with pycolmap, written as a COLMAP dataset
    that map, evaluate, slam and pseudo-label read."""
    from slamreloc.datasets.rosbag import default_topics
    from slamreloc.sfm import SfmConfig, print_sfm_summary, run_sfm

    if default_topics().pose:
        raise InputError("`topic` pose=: sfm makes the poses from the images and reads none")

    config = SfmConfig(camera=camera, fix_intrinsics=fix_intrinsics, matching=matching.value,
                       mapper=mapper.value, overlap=overlap, max_features=max_features, fps=fps,
                       split=split, scale=scale, scale_from_depth=scale_from_depth,
                       min_registered=min_registered, select=select,
                       min_parallax=min_parallax)
    print_sfm_summary(run_sfm(source, out, config))


@app.command()
def export(
    map_dir: Annotated[Path, typer.Argument(metavar="MAP", help="map folder")],
    colmap: Annotated[Optional[Path], typer.Option(
        help="write a COLMAP text model (cameras, images, points3D) into this folder")] = None,
    ply: Annotated[Optional[Path], typer.Option(help="write the coloured points (PLY)")] = None,
    tum: Annotated[Optional[Path], typer.Option(
        help="write the training poses (TUM, camera-to-world)")] = None,
    dataset: Annotated[Optional[Path], typer.Option(
        help="dataset for colours and image names (default: the one the map records); "
             "refused unless it holds the map's images (docs/formats.md, 'Export')")] = None,
) -> None:
    """Export MAP's labelled points and training cameras to COLMAP, PLY and TUM."""
    from slamreloc.map.export import export_map
    from slamreloc.runtime.progress import console, shown

    s = export_map(map_dir, colmap, ply, tum, dataset)
    written = ", ".join(str(p) for p in (colmap, ply, tum) if p is not None)
    colours = ("colours from the images" if s.get("coloured") == s.get("points") else
               "grey: no image of the map's frames at hand" if not s.get("coloured") else
               f"{s['coloured']} coloured from the images, the rest grey: their frames' "
               "images are not at hand")
    points = (f"{s['points']} points ({s['observations']} observations, {colours}), "
              if "points" in s else "")
    console.print(f"[green]exported[/green] {points}{s['frames']} cameras to {shown(written)}")


@app.command()
def demo(
    workdir: Annotated[Path, typer.Option(help="where the scene, map and reports go")] =
    Path("slamreloc-demo"),
    no_viewer: Annotated[bool, typer.Option("--no-viewer", help="do not serve the viewer")] =
    False,
    port: Annotated[int, typer.Option(
        help="viewer port (the next free one if busy; 0: any free one)")] = 8080,
) -> None:
    """The main job on the embedded synthetic scene (about 10 min on 2 CPU cores).

    Stages, each with progress bars, all written to --workdir:
    1. render the synthetic room: map, query, kidnap and unlabelled sequences
    2. map: SIFT features, labels from depth, surface, regressor training
    3. relocalize the query sequence: the regressor and the matching baseline
    4. SLAM backend on the kidnap sequence, the camera kidnapped twice
    5. map update from the unlabelled sequence (pseudo-labels), scored again
    6. result tables and the next commands to try
    7. the web viewer of it all until Ctrl-C (not with --no-viewer)"""
    from slamreloc.cli.demo import run_demo

    if not no_viewer:  # the port's rule before the stages, not after them
        from slamreloc.viewer.server import check_address

        check_address("127.0.0.1", port)
    run_demo(workdir, viewer=not no_viewer, port=port)


@app.command()
def slam(
    dataset: Annotated[Path, typer.Argument(
        metavar="DATASET", help="RGB-D dataset (7-Scenes, TUM, synthetic, a ROS bag)")],
    report: Annotated[Path, typer.Option("--report", help="REPORT.json to write")],
    map_dir: Annotated[Optional[Path], typer.Option(
        "--map", help="map folder to relocalize against (with --out: the map to extend, "
                      "which is kept as it is)")] = None,
    out: Annotated[Optional[Path], typer.Option(
        "--out", help="learn a map while tracking and write it to this folder (every "
                      "--save-every seconds, at the end, on Ctrl-C); from nothing without --map")]
    = None,
    save_every: Annotated[Optional[float], typer.Option(
        help="seconds between writes of the --out map (0: only at the end; default 30); only "
             "with --out")] = None,
    learn_every: Annotated[Optional[int], typer.Option(
        help="train the --out map on the tracker's thread, one round every N keyframes: the "
             "session is reproducible (its map does not depend on the machine's speed) and "
             "tracking waits for each round; default: rounds in the background, each as soon "
             "as the last ended; only with --out")] = None,
    sift_upsample: Annotated[bool, typer.Option(
        "--sift-upsample", help="the --out map's SIFT starts at twice the image's resolution: "
        "more keypoints on small images (under about 640x480); only with --out learning from "
        "nothing (extending a --map keeps that map's features)")] = False,
    split: Annotated[str, typer.Option(
        help="split, role or sequence names to track, or a comma-separated list of them "
             "(each sequence once)")] = "test",
    kidnap_every: Annotated[int, typer.Option(
        help="teleport the camera after every N processed frames (0: never)")] = 0,
    kidnap_skip: Annotated[Optional[int], typer.Option(
        help="frames dropped at each kidnapping (default 20); only with --kidnap-every")] =
    None,
    kidnap_from: Annotated[Optional[int], typer.Option(
        help="processed frames before the first kidnapping (default: --kidnap-every); only "
             "with --kidnap-every")] = None,
    odometry: Annotated[str, typer.Option(
        help="auto | kiss-icp | open3d | a TUM trajectory file from another system | "
             "topic:/NAME, a pose topic of a ROS bag DATASET (auto: kiss-icp on unregistered "
             "depth, open3d RGB-D on registered depth)")] = "auto",
    trajectory: Annotated[Optional[Path], typer.Option(
        help="write the map-frame trajectory (TUM, camera-to-world)")] = None,
    poses: Annotated[Optional[Path], typer.Option(
        metavar="FILE", help=POSES_HELP + "; the ground truth of the ATE")] = None,
) -> None:
    """Track a split with odometry, relocalize after tracking loss and at keyframes, optimise
    the pose graph in the map frame; report ATE, recoveries and loop closures. With --out,
    learn the map while tracking (from nothing, or extending --map) and save it."""
    from slamreloc.cli import jobs

    check_slam_options(map_dir, out, save_every, sift_upsample, kidnap_every, kidnap_skip,
                       kidnap_from, learn_every)
    live = None
    if sift_upsample or learn_every is not None:
        from slamreloc.slam.live_map import LiveMapConfig

        live = LiveMapConfig(feature_options={"upsample": True} if sift_upsample else {})
        if learn_every is not None:
            live = replace(live, train_every=learn_every,
                           learner=replace(live.learner, background=False))
    jobs.slam(dataset, map_dir, report, split, kidnap_every,
              20 if kidnap_skip is None else kidnap_skip, odometry, trajectory, poses=poses,
              out=out, save_every_s=30.0 if save_every is None else save_every,
              kidnap_from=-1 if kidnap_from is None else kidnap_from, live=live)


def check_slam_options(map_dir: Path | None, out: Path | None, save_every: float | None,
                       sift_upsample: bool, kidnap_every: int, kidnap_skip: int | None,
                       kidnap_from: int | None, learn_every: int | None = None) -> None:
    """InputError for an option given where it has no effect (None / False: not given): it
    would be ignored without a word. One line naming both options."""
    if out is None and save_every is not None:
        raise InputError("--save-every applies only with --out (the map learned while "
                         "tracking is written every --save-every seconds): give --out, or "
                         "leave --save-every out")
    if sift_upsample and out is None:
        raise InputError("--sift-upsample applies only with --out (the features of the map "
                         "learned while tracking): give --out, or leave --sift-upsample out")
    if sift_upsample and map_dir is not None:
        raise InputError("--sift-upsample has no effect with --map: the --out map extends "
                         "--map and keeps its features; leave --sift-upsample out")
    if learn_every is not None and out is None:
        raise InputError("--learn-every applies only with --out (the rounds of the map learned "
                         "while tracking): give --out, or leave --learn-every out")
    check_range("--learn-every", learn_every, 1, MAX_FRAMES)  # keyframes between rounds
    check_range("--kidnap-every", kidnap_every, 0, MAX_FRAMES)
    check_range("--kidnap-skip", kidnap_skip, 0, MAX_FRAMES)
    check_range("--kidnap-from", kidnap_from, 0, MAX_FRAMES)
    for flag, value in (("--kidnap-skip", kidnap_skip), ("--kidnap-from", kidnap_from)):
        if value is not None and kidnap_every == 0:
            raise InputError(f"{flag} applies only with --kidnap-every N (N > 0; 0: the camera "
                             f"is never kidnapped): give --kidnap-every, or leave {flag} out")


@app.command()
def view(
    map_dir: Annotated[Path, typer.Argument(metavar="MAP", help="map folder")],
    trajectory: Annotated[Optional[list[Path]], typer.Option(
        help="TUM trajectory (repeatable); a file named *gt* / *groundtruth* is ground truth")]
    = None,
    report: Annotated[Optional[list[Path]], typer.Option(
        help="REPORT.json of evaluate, slam or pseudo-label (repeatable)")] = None,
    dataset: Annotated[Optional[Path], typer.Option(
        help="dataset folder for images and ground truth (default: the one the map records)")]
    = None,
    port: Annotated[int, typer.Option(
        help="port (the next free one if busy; 0: any free one, printed)")] = 8080,
    host: Annotated[str, typer.Option(help="address to bind (0.0.0.0 exposes it)")] =
    "127.0.0.1",
    max_points: Annotated[int, typer.Option(help="voxel-downsample the map beyond this")] =
    500_000,
    poses: Annotated[Optional[Path], typer.Option(
        metavar="FILE", help=POSES_HELP + "; the ground truth shown")] = None,
) -> None:
    """Serve a web viewer (viser) of MAP with trajectories and reports, until Ctrl-C."""
    from slamreloc.viewer import ViewerInputs, serve

    serve(ViewerInputs(map_dir, list(trajectory or []), list(report or []), dataset, host, port,
                       max_points, poses=poses), echo=lambda line: print(line, flush=True))


def _print_map(scene_map) -> None:
    from slamreloc.runtime.progress import console, shown

    info = scene_map.info
    console.print(f"[green]map written[/green] to {shown(scene_map.root)}: {info.regressor_arch} "
                  f"regressor ({info.n_parameters / 1e6:.2f} M parameters, trained in "
                  f"{info.train_config.precision}, {scene_map.size_bytes() / 1e6:.1f} MB), "
                  f"trained on {info.n_labelled} labelled keypoints")
    poses = info.poses_source
    if poses != "dataset":
        console.print(f"[green]poses[/green]: from {shown(poses)} (--poses), not the dataset's")
    if not info.metric:
        console.print("[yellow]units[/yellow]: the dataset's SfM units, not metres (it was "
                      "made by `slamreloc sfm` without --scale or --scale-from-depth)")


@cache
def _flags() -> dict[str, str]:
    """Each option's field name -> its flag, over every command (one name, one flag)."""
    from typer.main import get_command

    root = get_command(app)
    commands = [root, *getattr(root, "commands", {}).values()]
    flags = {p.name: next(o for o in p.opts if o.startswith("--"))
             for c in commands for p in c.params
             if p.param_type_name == "option" and any(o.startswith("--") for o in p.opts)}
    for p in root.params:  # options of the program, not of a command: they go before it
        if p.name in flags:
            flags[p.name] = f"slamreloc {flags[p.name]}"
    return flags


def with_flags(message: str) -> str:
    """A library message as the command line says it: a setting named `field` (backticks,
    `slamreloc.errors`) becomes its flag where it is one of the commands' options (the
    program's own, `--limit` and `--topic`, as `slamreloc --topic`: they precede the
    command)."""
    flags = _flags()
    return re.sub(r"`([a-z][a-z0-9_]*)`", lambda m: flags.get(m[1], m[0]), message)
