"""Poses for unposed images: structure from motion with pycolmap, written as a COLMAP dataset.

    slamreloc sfm INPUT --out DATASET

INPUT is a folder of images, a video file (sampled at `fps`), or any dataset slamreloc reads
(7-Scenes, TUM, a ROS bag, ...; its poses are ignored, its intrinsics are the starting guess
and its depth can fix the metric scale). The stages: import (images copied, video frames
written as JPEG), SIFT extraction, matching (sequential for ordered input, exhaustive for
small sets), global (GLOMAP; the default for 100 images or more with a known camera) or
incremental mapping (COLMAP's; the default otherwise), then the scale: `scale_from_depth`
(median ratio of measured depth to SfM depth over all observations) or a user factor.
DATASET is what `load_dataset` reads as a COLMAP project:

    DATASET/images/NAME          the images, NAME as the model lists them
    DATASET/sparse/0/*.bin       cameras, images (registered ones), points3D
    DATASET/sfm.json             the summary: registered and unregistered images, points,
                                 mean track length, reprojection error, scale and whether the
                                 units are metres, timings

DATASET is written atomically (a temporary sibling renamed at the end): nothing is left half
written when SfM fails or registers too few images.
"""

from __future__ import annotations

import os
import shutil
import tempfile
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path, PurePosixPath

import numpy as np

from slamreloc.camera_models import MODELS, PARAMS, colmap_head
from slamreloc.errors import InputError
from slamreloc.io.fileio import check_outputs, write_json
from slamreloc.io.images import check_encoded_image
from slamreloc.runtime.progress import console, make_progress
from slamreloc.types import Camera
from slamreloc.io.video import is_video, video_frames

SFM_JSON = "sfm.json"
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp")
MATCHING = ("auto", "sequential", "exhaustive")
MAPPERS = ("auto", "global", "incremental")
EXHAUSTIVE_UP_TO = 60  # images; beyond, "auto" matches sequentially
GLOBAL_FROM = 100  # images; "auto" maps smaller sets (and unknown cameras) incrementally
EXTRACT_CHUNK = 20  # images per extraction call (progress granularity)
# images; sequential matching of up to this many uses COLMAP's brute-force SIFT matcher: exact,
# so the same input gives the same matches. A video's images are linked as a chain, and one link
# lost breaks the model: with the faster faiss-based matcher, whose matches can differ from run
# to run, a 30-frame synthetic video once registered 21 images instead of 29. Exact matching
# takes 7x as long (10 s instead of 1.4 s there, 2 cores), so exhaustive matching (where many
# pairs link each image) and longer sequences keep the faiss-based matcher
EXACT_MATCHING_UP_TO = 100
SEED = 0  # COLMAP's RANSAC and GLOMAP's initialisations: the same input gives the same model


@dataclass(frozen=True)
class SfmConfig:
    """camera: "" (the dataset's camera, else SIMPLE_RADIAL with COLMAP's focal guess), a
    COLMAP model name (intrinsics estimated), or a COLMAP camera string (the starting
    intrinsics; kept fixed with `fix_intrinsics`). scale: metres per SfM unit, given; or
    `scale_from_depth` where the input has depth."""

    camera: str = ""
    fix_intrinsics: bool = False
    matching: str = "auto"
    # auto: global for 100 images or more with a known camera (a dataset's, --fix-intrinsics),
    # else incremental. Global (GLOMAP) mapped RedKitchen's 400 images in 3.3 min on 2 cores,
    # incremental in more than 15; but on 20-40 synthetic images global positioning failed or
    # returned a wrong model (0.2 px reprojection error, 8 deg off), incremental did not
    mapper: str = "auto"
    overlap: int = 10  # sequential matching: each image with the next `overlap`
    max_features: int = 4096
    max_image_size: int = 1600  # pixels, longer side, for extraction
    fps: float = 2.0  # video: frames sampled per second
    split: str = "all"  # dataset input: which frames
    scale: float | None = None
    scale_from_depth: bool = False
    min_registered: float = 0.5  # fewer registered images than this share is an error

    def __post_init__(self) -> None:
        if self.matching not in MATCHING:
            raise InputError(f"--matching must be one of {', '.join(MATCHING)}, got "
                             f"{self.matching!r}")
        if self.mapper not in MAPPERS:
            raise InputError(f"--mapper must be one of {', '.join(MAPPERS)}, got "
                             f"{self.mapper!r}")
        if self.scale is not None and not 0 < self.scale < 1e6:
            raise InputError(f"--scale must be a positive number of metres per SfM unit, got "
                             f"{self.scale}")
        if self.scale is not None and self.scale_from_depth:
            raise InputError("--scale and --scale-from-depth: give one of them")
        initial_camera(self, None)  # a bad --camera fails before any work
        for name, low, high in (("overlap", 1, 1000), ("max_features", 100, 1 << 16),
                                ("max_image_size", 64, 1 << 16), ("fps", 1e-3, 1000),
                                ("min_registered", 0.0, 1.0)):
            v = getattr(self, name)
            if not low <= v <= high:
                raise InputError(f"--{name.replace('_', '-')} must be in {low}..{high}, got {v}")


@dataclass
class SfmInput:
    """What SfM runs on: image names (relative, POSIX) written under `images_dir`, the first
    camera guess, and the depth (metres, in the image's pixels) of a name where known."""

    kind: str  # "video" | "images" | "dataset"
    names: list[str]
    camera: Camera | None = None
    depth_of: Callable[[str], np.ndarray | None] | None = None
    sequential: bool = True  # ordered input (video, sequences): sequential matching
    notes: dict = field(default_factory=dict)


def _is_image_file(path: Path) -> bool:
    return path.suffix.lower() in IMAGE_SUFFIXES and path.is_file()


def collect_images(source: Path, images_dir: Path, config: SfmConfig,
                   progress: bool = True) -> SfmInput:
    """Copy (or, for a video, decode and write) the input's images into `images_dir`."""
    source = Path(source)
    if is_video(source):
        return _collect_video(source, images_dir, config, progress)
    if source.is_dir() and not _looks_like_dataset(source):
        return _collect_folder(source, images_dir, progress)
    from slamreloc.datasets import load_dataset

    return _collect_dataset(load_dataset(source), images_dir, config, progress)


def _looks_like_dataset(root: Path) -> bool:
    from slamreloc.datasets.colmap import is_colmap
    from slamreloc.datasets.sevenscenes import is_sevenscenes
    from slamreloc.datasets.tum import is_tum

    if (root / "metadata.yaml").is_file():  # a ROS 2 bag
        return True
    return is_tum(root) or is_colmap(root) or is_sevenscenes(root)


def _collect_video(path: Path, images_dir: Path, config: SfmConfig,
                   progress: bool) -> SfmInput:
    import cv2

    names = []
    folder = images_dir / path.stem
    folder.mkdir(parents=True)
    frames = video_frames(path, config.fps)  # a file FFmpeg cannot open fails here
    with make_progress() if progress else _NoBar() as bar:
        task = bar.add_task("decoding video", total=None, rate="")
        for t, rgb in frames:
            name = f"{path.stem}/frame-{len(names):06d}.jpg"
            if not cv2.imwrite(str(images_dir / name), rgb[:, :, ::-1],
                               [cv2.IMWRITE_JPEG_QUALITY, 95]):
                raise InputError(f"{images_dir / name}: could not write a video frame")
            names.append(name)
            bar.update(task, advance=1, rate=f"t={t:7.1f} s")
    return SfmInput("video", names, notes={"video": str(path), "fps": config.fps})


def _collect_folder(root: Path, images_dir: Path, progress: bool) -> SfmInput:
    paths = sorted(p for p in root.rglob("*") if _is_image_file(p))
    if not paths:
        raise InputError(f"{root}: no images ({', '.join(IMAGE_SUFFIXES)}) in this folder, and "
                         "it is not a dataset slamreloc reads")
    names = []
    for path in _tracked(paths, "copying images", progress):
        check_encoded_image(path.read_bytes(), path)
        name = path.relative_to(root).as_posix()
        (images_dir / name).parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(path, images_dir / name)
        names.append(name)
    return SfmInput("images", names, sequential=len(names) > EXHAUSTIVE_UP_TO)


def _collect_dataset(dataset, images_dir: Path, config: SfmConfig,
                     progress: bool) -> SfmInput:
    from slamreloc.rgbd import frame_depth

    frames = dataset.frames(config.split)
    if not frames:
        raise InputError(f"{dataset.root}: split '{config.split}' has no frames")
    if config.scale_from_depth and not any(f.depth_path is not None for f in frames):
        raise InputError(f"{dataset.root}: --scale-from-depth needs depth, and split "
                         f"'{config.split}' has none (give --scale M instead)")
    by_name = {}
    for frame in _tracked(frames, "copying images", progress):
        named = PurePosixPath(frame.name).suffix.lower() in IMAGE_SUFFIXES
        name = frame.name if named else f"{frame.name}{frame.image_path.suffix.lower()}"
        (images_dir / name).parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(frame.image_path, images_dir / name)
        by_name[name] = frame

    def depth_of(name: str) -> np.ndarray | None:
        frame = by_name[name]
        return None if frame.depth_path is None else frame_depth(frame, dataset)

    has_depth = any(f.depth_path is not None for f in frames)
    return SfmInput("dataset", list(by_name), frames[0].camera,
                    depth_of if has_depth else None,
                    notes={"input_dataset": str(dataset.root), "split": config.split,
                           "depth": has_depth})


class _NoBar:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False

    def add_task(self, *a, **k):
        return 0

    def update(self, *a, **k):
        pass


def _tracked(items, description: str, progress: bool):
    from slamreloc.runtime.progress import track

    return track(items, description, enabled=progress)


def initial_camera(config: SfmConfig, given: Camera | None) -> tuple[str, str]:
    """(COLMAP model, comma-separated starting parameters or "" for COLMAP's guess)."""
    text = config.camera.strip()
    if text and len(text.split()) == 1:
        model = text.upper()
        if model not in MODELS:
            raise InputError(f"--camera: unknown camera model {text[:40]!r} (known: "
                             f"{', '.join(MODELS)})")
        if given is None:
            return model, ""
        # the dataset's intrinsics, in the asked model (distortion starts at zero)
        head = colmap_head(model, *given.params())
        params = [*head, *([0.0] * (len(PARAMS[model]) - len(head)))]
        return model, ",".join(repr(float(p)) for p in params)
    camera = Camera.parse(text, "--camera") if text else given
    if camera is None:
        return "SIMPLE_RADIAL", ""
    return camera.model, ",".join(repr(float(p)) for p in camera.colmap_params())


def _quiet_colmap() -> None:
    import pycolmap

    pycolmap.logging.minloglevel = 2  # warnings and errors only; slamreloc shows progress


def run_sfm(source: Path, out: Path, config: SfmConfig = SfmConfig(),
            progress: bool = True) -> dict:
    """Run SfM on `source` and write the COLMAP dataset `out`; returns the summary."""
    source, out = Path(source), Path(out)
    if not source.exists():
        raise InputError(f"{source}: not found (a folder of images, a video or a dataset)")
    check_outputs({"--out": out}, {"the input": source}, folders=("--out",))
    if config.scale_from_depth and (is_video(source) or source.is_dir()
                                    and not _looks_like_dataset(source)):
        raise InputError(f"{source}: --scale-from-depth needs depth, and a video or a folder "
                         "of images has none (give --scale M instead)")
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise InputError(f"{out}: exists and is not empty; choose a new folder")
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.parent / f"{out.name}.tmp-{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir()
    try:
        summary = _run(source, tmp, config, progress)
        if out.exists():
            out.rmdir()
        os.replace(tmp, out)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    summary["dataset"] = str(out)
    return summary


def _run(source: Path, root: Path, config: SfmConfig, progress: bool) -> dict:
    import pycolmap

    _quiet_colmap()
    pycolmap.set_random_seed(SEED)
    timings = {}
    t0 = time.perf_counter()
    images_dir = root / "images"
    images_dir.mkdir()
    inp = collect_images(source, images_dir, config, progress)
    if len(inp.names) < 2:
        raise InputError(f"{source}: SfM needs at least 2 images, found {len(inp.names)}")
    timings["import_s"] = time.perf_counter() - t0
    model, params = initial_camera(config, inp.camera)
    # a dataset's camera is a calibration: kept unless --camera asks for another model
    fixed = config.fix_intrinsics or (inp.camera is not None and not config.camera.strip())
    with tempfile.TemporaryDirectory(prefix="slamreloc-sfm-") as work:
        database = Path(work) / "database.db"
        t0 = time.perf_counter()
        _extract(database, images_dir, inp.names, model, params, config, progress)
        timings["features_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        matching = config.matching if config.matching != "auto" else (
            "sequential" if inp.sequential else "exhaustive")
        exact = matching == "sequential" and len(inp.names) <= EXACT_MATCHING_UP_TO
        _match(database, matching, exact, config, progress)
        timings["matching_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        mapper = config.mapper if config.mapper != "auto" else (
            "global" if fixed and len(inp.names) >= GLOBAL_FROM else "incremental")
        rec, other_models = _map(database, images_dir, Path(work) / "sparse", inp.names,
                                 mapper, fixed, progress)
        timings["mapping_s"] = time.perf_counter() - t0
    registered = [] if rec is None else sorted(im.name for im in rec.images.values()
                                                if im.has_pose)
    unregistered = sorted(set(inp.names) - set(registered))
    share = len(registered) / len(inp.names)
    if len(registered) < 3 or share < config.min_registered:
        raise InputError(
            f"{source}: SfM registered only {len(registered)} of {len(inp.names)} images "
            f"({100 * share:.0f} %, at least {100 * config.min_registered:.0f} % needed); try "
            "--matching exhaustive, a camera model that fits the lens (--camera OPENCV or "
            "OPENCV_FISHEYE), more overlap (a higher --fps for video, --overlap), or lower "
            "--min-registered")
    scale, scale_note = 1.0, "unknown (SfM units)"
    if config.scale is not None:
        scale, scale_note = config.scale, "metres (user scale)"
    elif config.scale_from_depth:
        if inp.depth_of is None:
            raise InputError(f"{source}: --scale-from-depth needs depth, and this input has "
                             "none (give --scale M instead)")
        t0 = time.perf_counter()
        scale, spread, n_obs = depth_scale(rec, inp.depth_of, progress)
        timings["scale_s"] = time.perf_counter() - t0
        scale_note = f"metres (from depth: {n_obs} observations, spread {100 * spread:.1f} %)"
    if scale != 1.0:
        rec.transform(pycolmap.Sim3d(scale, pycolmap.Rotation3d(), np.zeros(3)))
    sparse = root / "sparse" / "0"
    sparse.mkdir(parents=True)
    rec.write_binary(str(sparse))
    cam = next(iter(rec.cameras.values()))
    summary = {
        "input": str(source), "input_kind": inp.kind, **inp.notes,
        "matching": matching, "exact_matching": exact, "mapper": mapper,
        "intrinsics_fixed": fixed,
        "n_images": len(inp.names), "n_registered": len(registered),
        "unregistered": unregistered, "n_other_models": other_models,
        "n_points": int(rec.num_points3D()),
        "mean_track_length": float(rec.compute_mean_track_length()),
        "mean_reprojection_error_px": float(rec.compute_mean_reprojection_error()),
        "camera": f"{cam.model.name} {cam.width} {cam.height} "
                  + " ".join(f"{p:.6g}" for p in cam.params),
        "scale": scale, "metric": config.scale is not None or config.scale_from_depth,
        "units": scale_note, "config": asdict(config),
        "timings_s": {**timings, "total_s": sum(timings.values())},
    }
    write_json(root / SFM_JSON, summary)
    return summary


def _extract(database: Path, images_dir: Path, names: list[str], model: str, params: str,
             config: SfmConfig, progress: bool) -> None:
    import pycolmap

    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = model
    reader.camera_params = params
    options = pycolmap.FeatureExtractionOptions()
    options.max_image_size = config.max_image_size
    options.sift.max_num_features = config.max_features
    chunks = [names[i:i + EXTRACT_CHUNK] for i in range(0, len(names), EXTRACT_CHUNK)]
    with make_progress() if progress else _NoBar() as bar:
        task = bar.add_task("sfm: features", total=len(names), rate="")
        for chunk in chunks:
            pycolmap.extract_features(database, images_dir, chunk,
                                      pycolmap.CameraMode.SINGLE, reader, options,
                                      device=pycolmap.Device.cpu)
            reader.existing_camera_id = 1  # the camera the first chunk made: one for all
            bar.update(task, advance=len(chunk))


def _match(database: Path, matching: str, exact: bool, config: SfmConfig,
           progress: bool) -> None:
    import pycolmap

    options = pycolmap.FeatureMatchingOptions()
    options.sift.cpu_brute_force_matcher = exact
    verification = pycolmap.TwoViewGeometryOptions()
    verification.ransac.random_seed = SEED
    with make_progress() if progress else _NoBar() as bar:
        bar.add_task(f"sfm: {matching} matching", total=None, rate="")
        if matching == "sequential":
            pairing = pycolmap.SequentialPairingOptions()
            pairing.overlap = config.overlap
            pairing.quadratic_overlap = True
            pycolmap.match_sequential(database, options, pairing, verification,
                                      device=pycolmap.Device.cpu)
        else:
            pycolmap.match_exhaustive(database, options, pycolmap.ExhaustivePairingOptions(),
                                      verification, device=pycolmap.Device.cpu)


def _map(database: Path, images_dir: Path, sparse: Path, names: list[str], mapper: str,
         fixed: bool, progress: bool):
    """(the largest reconstruction or None, number of other, smaller models)."""
    import pycolmap

    sparse.mkdir()
    with make_progress() if progress else _NoBar() as bar:
        task = bar.add_task(f"sfm: {mapper} mapping", total=len(names), rate="")
        if mapper == "global":
            if not fixed:  # focal lengths from the fundamental matrices first (GLOMAP)
                calibration = pycolmap.ViewGraphCalibrationOptions()
                calibration.random_seed = SEED
                pycolmap.calibrate_view_graph(database, calibration)
            options = pycolmap.GlobalPipelineOptions()
            options.random_seed = options.mapper.random_seed = SEED
            ba = options.mapper.bundle_adjustment
            ba.refine_focal_length = ba.refine_extra_params = not fixed
            ba.refine_principal_point = False
            models = pycolmap.global_mapping(database, images_dir, sparse, options)
            bar.update(task, completed=max((r.num_reg_images() for r in models.values()),
                                           default=0))
        else:
            options = pycolmap.IncrementalPipelineOptions()
            options.random_seed = SEED
            options.ba_refine_focal_length = not fixed
            options.ba_refine_extra_params = not fixed
            options.ba_refine_principal_point = False
            seen = [0]

            def registered(n: int) -> None:  # images may be registered again: cap at all
                seen[0] += n
                bar.update(task, completed=min(seen[0], len(names)))

            models = pycolmap.incremental_mapping(
                database, images_dir, sparse, options,
                initial_image_pair_callback=lambda: registered(2),
                next_image_callback=lambda: registered(1))
    if not models:
        return None, 0
    ordered = sorted(models.values(), key=lambda r: r.num_reg_images(), reverse=True)
    return ordered[0], len(ordered) - 1


def depth_scale(rec, depth_of: Callable[[str], np.ndarray | None],
                progress: bool = True) -> tuple[float, float, int]:
    """(metres per SfM unit, relative spread (IQR / 2 / median), observations used): the
    median over all observations of measured depth over SfM depth."""
    ratios = []
    images = [im for im in rec.images.values() if im.has_pose]
    for image in _tracked(images, "sfm: scale from depth", progress):
        depth = depth_of(image.name)
        if depth is None:
            continue
        h, w = depth.shape
        cam_from_world = image.cam_from_world()
        for p2d in image.points2D:
            if not p2d.has_point3D():
                continue
            u, v = int(p2d.xy[0]), int(p2d.xy[1])  # COLMAP: pixel centres at +0.5
            if not (0 <= u < w and 0 <= v < h) or depth[v, u] <= 0:
                continue
            z = (cam_from_world * rec.points3D[p2d.point3D_id].xyz)[2]
            if z > 0:
                ratios.append(depth[v, u] / z)
    if len(ratios) < 20:
        raise InputError(f"only {len(ratios)} SfM points have a depth measurement; "
                         "--scale-from-depth needs depth registered to the images")
    ratios = np.asarray(ratios)
    q1, med, q3 = np.percentile(ratios, [25, 50, 75])
    return float(med), float((q3 - q1) / 2 / med), len(ratios)


def print_sfm_summary(s: dict) -> None:
    unreg = s["unregistered"]
    listed = ", ".join(unreg[:5]) + (f", ... ({len(unreg)} in {s['dataset']}/{SFM_JSON})"
                                     if len(unreg) > 5 else "")
    console.print(
        f"[green]SfM dataset written[/green] to {s['dataset']}: {s['n_registered']}/"
        f"{s['n_images']} images registered, {s['n_points']} points, mean track length "
        f"{s['mean_track_length']:.1f}, mean reprojection error "
        f"{s['mean_reprojection_error_px']:.2f} px, units {s['units']}, camera {s['camera']}, "
        f"{s['timings_s']['total_s']:.0f} s")
    if unreg:
        console.print(f"[yellow]not registered[/yellow]: {listed}")
