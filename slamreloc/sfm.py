"""Poses for unposed images: structure from motion with pycolmap, written as a COLMAP dataset.

    slamreloc sfm INPUT --out DATASET

INPUT is a folder of images, a video file (sampled at `fps`), or any dataset slamreloc reads
(7-Scenes, TUM, a ROS bag, ...; its poses are ignored, its intrinsics are the starting guess
and its depth can fix the metric scale). The stages: import (images copied, video frames
written as JPEG; with `select` "parallax", the default for a video, only the frames with
enough parallax to the last one kept: `KeyframeSelector`), SIFT extraction, matching
(sequential for ordered input, exhaustive for small sets), global (GLOMAP; the default for 100
images or more with a known camera) or incremental mapping (COLMAP's; the default
otherwise), then the scale: `scale_from_depth` (median ratio of measured depth to SfM depth
over all observations) or a user factor.
DATASET is what `load_dataset` reads as a COLMAP project:

    DATASET/images/NAME          the images, NAME as the model lists them
    DATASET/sparse/0/*.bin       cameras, images (registered ones), points3D
    DATASET/sfm.json             the summary: registered and unregistered images, points,
                                 mean track length, reprojection error, scale and whether the
                                 units are metres, timings

DATASET is written atomically (a temporary sibling renamed at the end): nothing is left half
written when SfM fails or registers too few images. The error then names the cause it
measured: no matching pairs, or too little parallax (`parallax_deg` on the matched pairs of
the widest and of neighbouring views), with the advice that fits it.
"""

from __future__ import annotations

import errno
import os
import stat
import shutil
import tempfile
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path, PurePosixPath

import numpy as np

from slamreloc.camera_models import MODELS, PARAMS, colmap_head
from slamreloc.errors import InputError
from slamreloc.io.outputs import (check_outputs, is_file_debris_name, make_temp_dir,
                                  naming_output, still_as_checked, temp_dir_path, what_is_there,
                                  write_json)
from slamreloc.io.fileio import is_link_loop
from slamreloc.io.folder_lock import Debris, folder_write_lock
from slamreloc.io.images import write_image
from slamreloc.io.video import is_video, video_frames
from slamreloc.runtime.progress import console, make_progress, shown
from slamreloc.types import Camera, frame_name_problem

SFM_JSON = "sfm.json"
# the photos of a folder, by name: every format both `read_image` and COLMAP read (PNG, JPEG,
# BMP, TIFF, PNM); a photo of another format (WebP: COLMAP's reader has none) is refused by
# name, never left out unsaid nor "not registered"
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".jpe", ".jfif", ".bmp", ".dib", ".tif", ".tiff",
                  ".ppm", ".pgm", ".pbm", ".pnm")
UNREAD_IMAGE_SUFFIXES = (".webp", ".gif", ".heic", ".heif", ".avif", ".jp2", ".jxl", ".dng",
                         ".cr2", ".nef", ".arw", ".raw")
# the first bytes of the formats COLMAP reads (PNG, JPEG, BMP, TIFF, PNM): a photo is taken by
# its content, not its name, since OpenCV (every other reader here) decodes more
COLMAP_IMAGE_MAGIC = (b"\x89PNG\r\n\x1a\n", b"\xff\xd8\xff", b"BM", b"II*\x00", b"MM\x00*",
                      b"P1", b"P2", b"P3", b"P4", b"P5", b"P6")
# formats OpenCV or a camera may give under another name, recognised to say which
OTHER_IMAGE_FORMATS = (
    ("WebP", lambda d: d[:4] == b"RIFF" and d[8:12] == b"WEBP"),
    ("GIF", lambda d: d[:4] == b"GIF8"),
    ("HEIC/AVIF", lambda d: d[4:8] == b"ftyp"),
    ("JPEG 2000", lambda d: d.startswith((b"\x00\x00\x00\x0cjP  ", b"\xff\x4f\xff\x51"))),
    ("JPEG XL", lambda d: d.startswith((b"\xff\x0a", b"\x00\x00\x00\x0cJXL "))),
    ("OpenEXR", lambda d: d[:4] == b"\x76\x2f\x31\x01"),
    ("Radiance HDR", lambda d: d.startswith((b"#?RADIANCE", b"#?RGBE"))),
)
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
# keyframe selection: "auto" selects by parallax for a video (its frames are already a sampling
# the user delegated) and keeps every photo of a folder or a dataset (each was chosen, and each
# dropped is an image without a pose)
SELECTIONS = ("auto", "all", "parallax")
# degrees: a frame is kept once its tracked points' median triangulation angle to the last kept
# frame reaches this (measured with the starting camera, as COLMAP's mapper measures it; it
# starts a model from a pair at PARALLAX_START_DEG). Chosen on 8 slow synthetic sequences (30
# photos over 5 cm, 0.8-1.5 m from a box before a wall: at the edge of what registers), none of
# them the tests': 0.75 deg registered 4 of them, 1 and 1.5 deg 3, 2 deg 1 (all 30 photos: 2 of
# the 4 run). A moving camera's frames are further apart than this: a video's are all kept
MIN_PARALLAX_DEG = 0.75
DEFAULT_FPS = 2.0  # frames sampled per second of a video
DEFAULT_OVERLAP = 10  # sequential matching: each image with the next 10
# COLMAP's incremental mapper starts a model from a pair whose points' median triangulation
# angle is at least init_min_tri_angle (16 deg), halved twice when no model starts: 4 deg
PARALLAX_START_DEG = 4.0
FOCAL_GUESS = 1.2  # COLMAP's prior focal length, times the longer image side
SELECT_SIZE = 480  # pixels, longer side of the grey frames selection tracks points on
SELECT_CORNERS = 500  # points tracked from each kept frame
MIN_TRACKED_SHARE = 0.5  # fewer of them tracked: the view moved on, the frame is kept
MIN_TRACKED = 20  # points; fewer cannot measure parallax
# share of the longer image side: a frame whose points moved this much is kept whatever its
# parallax. Above a near-duplicate's motion (the 5 cm sequences of MIN_PARALLAX_DEG: 2 % or
# less from the first frame to the last), under a moving camera's (the synthetic map
# sequence's frames, 13 cm apart: 10-19 % from one to the next)
MIN_MOTION = 0.05
DIAGNOSED_PAIRS = 30  # matched pairs measured for the error, widest and neighbouring each
MIN_PAIR_INLIERS = 15  # a pair counts as matched with this many verified inlier matches


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
    overlap: int | None = None  # sequential matching: each image with the next N (None: 10)
    max_features: int = 4096
    max_image_size: int = 1600  # pixels, longer side, for extraction
    fps: float | None = None  # video: frames sampled per second (None: 2)
    split: str = "all"  # dataset input: which frames
    scale: float | None = None
    scale_from_depth: bool = False
    min_registered: float = 0.5  # fewer registered images than this share is an error
    select: str = "auto"  # auto (parallax for a video, else all) | all | parallax
    min_parallax: float | None = None  # degrees, select "parallax" (None: MIN_PARALLAX_DEG)

    def __post_init__(self) -> None:
        if self.select not in SELECTIONS:
            raise InputError(f"`select` must be one of {', '.join(SELECTIONS)}, got "
                             f"{self.select!r}")
        if self.matching not in MATCHING:
            raise InputError(f"`matching` must be one of {', '.join(MATCHING)}, got "
                             f"{self.matching!r}")
        if self.mapper not in MAPPERS:
            raise InputError(f"`mapper` must be one of {', '.join(MAPPERS)}, got "
                             f"{self.mapper!r}")
        if self.scale is not None and not 1e-6 < self.scale < 1e6:  # poses stay in metres
            raise InputError(f"`scale` must be metres per SfM unit, over 1e-6 and under 1e6, "
                             f"got {self.scale:g}")
        if self.scale is not None and self.scale_from_depth:
            raise InputError("`scale` and `scale_from_depth`: give one of them")
        initial_camera(self, None)  # a bad --camera fails before any work
        if self.min_parallax is not None and self.select == "all":
            raise InputError("`min_parallax` is for `select` parallax; `select` all keeps every "
                             "image (leave `min_parallax` out)")
        if self.overlap is not None and self.matching == "exhaustive":
            raise InputError("`overlap` is for sequential matching; `matching` exhaustive "
                             "matches every pair (leave `overlap` out)")
        for name, low, high in (("overlap", 1, 1000), ("max_features", 100, 1 << 16),
                                ("max_image_size", 64, 1 << 16), ("fps", 1e-3, 1000),
                                ("min_registered", 0.0, 1.0), ("min_parallax", 0.01, 60.0)):
            v = getattr(self, name)
            if v is not None and not low <= v <= high:
                raise InputError(f"`{name}` must be in {low}..{high}, got {v}")


    @property
    def video_fps(self) -> float:
        """Frames sampled per second of a video: `fps`, else 2."""
        return DEFAULT_FPS if self.fps is None else self.fps

    @property
    def sequential_overlap(self) -> int:
        """Sequential matching pairs each image with the next this many: `overlap`, else 10."""
        return DEFAULT_OVERLAP if self.overlap is None else self.overlap

    @property
    def parallax_deg(self) -> float:
        """`select` parallax keeps an image at this median triangulation angle (degrees)."""
        return MIN_PARALLAX_DEG if self.min_parallax is None else self.min_parallax


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
    sizes: dict = field(default_factory=dict)  # (width, height) -> the first image of that size


def parallax_deg(x1: np.ndarray, x2: np.ndarray, focal: float = 1000.0) -> float | None:
    """The median triangulation angle (degrees) of corresponding points x1 <-> x2 of two views,
    (N, 2) normalized image coordinates ((pixel - principal point) / focal): the angle between
    each point's two viewing rays once the views' relative rotation is taken out, the rotation
    of their relative pose (pycolmap's LO-RANSAC on the essential matrix, 1 pixel of `focal`
    allowed; a camera that only turns: the rotation that best aligns the rays). A camera that
    only turns gives 0, one that moves 5 cm sideways, 1 m from the points it sees, about 3.
    None when it cannot be measured (fewer than 8 points, or no relative pose)."""
    import pycolmap

    x1, x2 = np.asarray(x1, np.float64), np.asarray(x2, np.float64)
    if len(x1) < 8:
        return None
    b1, b2 = (np.c_[x, np.ones(len(x))] for x in (x1, x2))
    b1 /= np.linalg.norm(b1, axis=1, keepdims=True)
    b2 /= np.linalg.norm(b2, axis=1, keepdims=True)

    def angle(r: np.ndarray, inliers=slice(None)) -> float:  # median, rays b1 and r^T b2
        cos = np.sum(b1[inliers] * (b2[inliers] @ r), 1)
        return float(np.degrees(np.median(np.arccos(np.clip(cos, -1.0, 1.0)))))

    # the rotation that best aligns the rays (Kabsch): all there is when the camera only
    # turned, where the essential matrix is degenerate
    u, _, vt = np.linalg.svd(b2.T @ b1)
    turn = u @ np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))]) @ vt  # b2 ~ turn b1
    if angle(turn) < 1e-3:
        return angle(turn)
    camera = pycolmap.Camera(model="SIMPLE_PINHOLE", width=2, height=2, params=[1.0, 0.0, 0.0])
    ransac = pycolmap.RANSACOptions()
    ransac.max_error = 1.0 / focal
    ransac.random_seed = SEED
    pose = pycolmap.estimate_relative_pose(camera, x1, camera, x2, ransac)
    if pose is None:
        return angle(turn)
    inliers = np.asarray(pose["inlier_mask"], bool)
    if inliers.sum() < 8:
        return None
    r = pose["cam2_from_cam1"].rotation.matrix()
    t = pose["cam2_from_cam1"].translation
    # and its "twisted pair", turned by 180 deg about the baseline, should the cheirality test
    # have picked that one for a baseline too short to tell
    twisted = (2 * np.outer(t, t) / max(float(t @ t), 1e-300) - np.eye(3)) @ r
    return min(angle(r, inliers), angle(twisted, inliers))


@dataclass
class _Reference:
    """A kept frame as selection compares with it: grey image, points to track, focal, centre."""

    grey: np.ndarray
    points: np.ndarray | None
    focal: float
    centre: np.ndarray


class KeyframeSelector:
    """Keyframes by parallax: of frames in order, keep the first, then each frame whose tracked
    points (corners tracked by pyramidal Lucas-Kanade, forward and back, on grey frames of at
    most SELECT_SIZE pixels) reach `min_parallax` degrees of median triangulation angle
    (`parallax_deg`) to the last kept frame. A frame whose points moved by MIN_MOTION of the
    image or more is kept whatever its parallax (a turn, or a plane seen while moving, whose
    essential matrix hides the parallax: the view has changed), and so is a frame selection
    cannot measure (too little texture, or the view moved on: fewer than half the points
    tracked). The last frame is kept from half of either. `focal`: the camera's focal length in
    pixels of `width`, where known; else COLMAP's prior, 1.2 x the longer side."""

    def __init__(self, min_parallax: float = MIN_PARALLAX_DEG, focal: float | None = None,
                 width: int | None = None) -> None:
        self.min_parallax = min_parallax
        self._focal = (focal, width) if focal and width else None
        self.n_candidates = 0
        self.n_kept = 0
        self.dropped: list = []

    def _grey(self, image: np.ndarray) -> np.ndarray:
        import cv2

        grey = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
        scale = SELECT_SIZE / max(grey.shape)
        if scale < 1:
            grey = cv2.resize(grey, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
        return grey

    def _reference(self, grey: np.ndarray) -> _Reference:
        import cv2

        h, w = grey.shape
        if self._focal is not None:
            focal = self._focal[0] * w / self._focal[1]
        else:
            focal = FOCAL_GUESS * max(h, w)
        points = cv2.goodFeaturesToTrack(grey, SELECT_CORNERS, 0.01, max(4, max(h, w) // 60))
        return _Reference(grey, points, focal, np.array([(w - 1) / 2, (h - 1) / 2]))

    def _change(self, ref: _Reference, grey: np.ndarray) -> tuple[float, float] | None:
        """(parallax in degrees, the points' median image motion as a share of the longer
        side) of `grey` against `ref`; None where it cannot be measured."""
        import cv2

        if ref.points is None or len(ref.points) < MIN_TRACKED or grey.shape != ref.grey.shape:
            return None  # nothing to measure with
        lk = dict(winSize=(21, 21), maxLevel=4,
                  criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01))
        ahead, ok1, _ = cv2.calcOpticalFlowPyrLK(ref.grey, grey, ref.points, None, **lk)
        back, ok2, _ = cv2.calcOpticalFlowPyrLK(grey, ref.grey, ahead, None, **lk)
        good = ((ok1[:, 0] == 1) & (ok2[:, 0] == 1)
                & (np.linalg.norm(back - ref.points, axis=2)[:, 0] < 1.0))
        if good.sum() < max(MIN_TRACKED, MIN_TRACKED_SHARE * len(good)):
            return None  # the view moved on
        p1, p2 = ref.points[good, 0].astype(np.float64), ahead[good, 0].astype(np.float64)
        parallax = parallax_deg((p1 - ref.centre) / ref.focal, (p2 - ref.centre) / ref.focal,
                                ref.focal)
        if parallax is None:
            return None
        return parallax, float(np.median(np.linalg.norm(p2 - p1, axis=1)) / max(grey.shape))

    def select(self, frames):
        """Yield the kept (key, image) of `frames`, an iterable of (key, image), image RGB or
        grey; `dropped` lists the others' keys."""
        ref = pending = None
        for key, image in frames:
            self.n_candidates += 1
            grey = self._grey(image)
            if ref is not None:
                change = self._change(ref, grey)
                if change is not None and change[0] < self.min_parallax \
                        and change[1] < MIN_MOTION:
                    self.dropped.append(key)
                    pending = (key, image, change)
                    continue
            self.n_kept += 1
            yield key, image
            ref, pending = self._reference(grey), None
        if pending is not None and (pending[2][0] >= self.min_parallax / 2
                                    or pending[2][1] >= MIN_MOTION / 2):
            self.dropped.pop()  # the last frame, for the baseline it adds
            self.n_kept += 1
            yield pending[0], pending[1]

    def summary(self) -> dict:
        return {"method": "parallax", "min_parallax_deg": self.min_parallax,
                "n_candidates": self.n_candidates, "n_kept": self.n_kept}


def _selector(config: SfmConfig, kind: str, camera: Camera | None) -> KeyframeSelector | None:
    """The keyframe selector `config` asks for on input of this kind, or None (keep all)."""
    if config.select == "all" or config.select == "auto" and kind != "video":
        return None
    text = config.camera
    if text and len(text.split()) > 1:
        camera = Camera.parse(text, "`camera`")
    if camera is None:
        return KeyframeSelector(config.parallax_deg)
    return KeyframeSelector(config.parallax_deg, camera.fx, camera.width)


def _report_selection(selector: KeyframeSelector | None, what: str, progress: bool) -> dict:
    if selector is None:
        return {}
    s = selector.summary()
    if progress:
        console.print(f"selection: kept {s['n_kept']} of {s['n_candidates']} {what} (parallax "
                      f"of {selector.min_parallax:g} deg or more to the last one kept)")
    return {"selection": s}


def checked_image(path: Path, size: tuple[int, int] | None = None
                  ) -> tuple[bytes, np.ndarray]:
    """(the bytes, the decoded RGB) of an image file SfM may take: bounded, complete (a JPEG
    with its scan data: headers alone, or a scan cut right after its header, are refused, not
    left for COLMAP to fail on or to read as a grey picture) and decoded in full; of `size`
    (width, height) where given (a dataset frame's: `size_problem`, the rule of the dataset's
    load). InputError naming the file otherwise."""
    from slamreloc.io.fileio import read_bytes
    from slamreloc.io.images import decode_rgb, size_problem

    data = read_bytes(path, "image", "max_image_bytes")
    if not data.startswith(COLMAP_IMAGE_MAGIC):  # named .jpg, but a WebP (a web download)
        kind = next((name for name, test in OTHER_IMAGE_FORMATS if test(data)), None)
        what = f"a {kind} image" if kind else "not a PNG, JPEG, BMP, TIFF or PNM image"
        raise InputError(f"{path}: {what} by its content (whatever its name), a format sfm "
                         "does not read (PNG, JPEG, BMP, TIFF and PNM are read): convert it, "
                         "or move it out")
    rgb = decode_rgb(data, path)  # `check_encoded_image`'s rules, every reader's
    problem = size and size_problem((rgb.shape[1], rgb.shape[0]), size)
    if problem:
        raise InputError(f"{path}: {problem}")
    return data, rgb


def _is_image_file(path: Path, root: Path) -> bool:
    """A photo of the folder `root` by its name; InputError where that name is no regular
    file (a folder, a pipe, a device, a broken link: it would vanish from the input unsaid)
    or could not name a frame (`frame_name_problem`: a line break in it)."""
    if path.suffix.lower() in UNREAD_IMAGE_SUFFIXES:
        raise InputError(f"{path}: a photo of a format sfm does not read (PNG, JPEG, BMP, "
                         "TIFF and PNM are read): convert it, or move it out")
    if path.suffix.lower() not in IMAGE_SUFFIXES:
        return False
    if not path.is_file():
        kind = ("a folder" if path.is_dir() else "a symbolic link loop" if is_link_loop(path)
                else "a broken link" if not path.exists() else "a pipe, device or socket")
        raise InputError(f"{path}: named as a photo but not a file ({kind})")
    problem = frame_name_problem(path.relative_to(root).as_posix())
    if problem:
        raise InputError(f"{path}: its name {problem}: rename the photo")
    return True


def collect_images(source: Path, images_dir: Path, config: SfmConfig,
                   progress: bool = True) -> SfmInput:
    """Copy (or, for a video, decode and write) the input's images into `images_dir`."""
    source = Path(source)
    if is_video(source):
        return _collect_video(source, images_dir, config, progress)
    if source.is_dir() and not _looks_like_dataset(source):
        return _collect_folder(source, images_dir, config, progress)
    from slamreloc.datasets import load_dataset

    return _collect_dataset(load_dataset(source), images_dir, config, progress)


def _looks_like_dataset(root: Path) -> bool:
    from slamreloc.datasets.colmap import is_colmap
    from slamreloc.datasets.rosbag import is_rosbag
    from slamreloc.datasets.sevenscenes import is_sevenscenes
    from slamreloc.datasets.tum import is_tum

    if is_rosbag(root):  # a ROS 2 bag folder (its reader names a metadata.yaml it cannot read)
        return True
    return is_tum(root) or is_colmap(root) or is_sevenscenes(root)


def video_frame_name(video: Path, index: int) -> str:
    """The frame name a video's `index`-th sampled frame gets (`STEM/frame-000012.jpg`)."""
    return f"{video.stem}/frame-{index:06d}.jpg"


def _collect_video(path: Path, images_dir: Path, config: SfmConfig,
                   progress: bool) -> SfmInput:
    import cv2

    names, sizes = [], {}
    folder = images_dir / path.stem
    folder.mkdir(parents=True)
    frames = video_frames(path, config.video_fps)  # a file FFmpeg cannot open fails here
    selector = _selector(config, "video", None)
    with make_progress() if progress else _NoBar() as bar:
        task = bar.add_task("decoding video", total=None, rate="")

        def sampled():  # (index among the sampled frames, RGB)
            for index, (t, rgb) in enumerate(frames):
                kept = "" if selector is None else f", {selector.n_kept} kept"
                bar.update(task, advance=1, rate=f"t={t:7.1f} s{kept}")
                yield index, rgb

        # a frame keeps its index among the sampled ones: the names show what selection dropped
        for index, rgb in sampled() if selector is None else selector.select(sampled()):
            name = video_frame_name(path, index)
            write_image(images_dir / name, rgb[:, :, ::-1], (cv2.IMWRITE_JPEG_QUALITY, 95))
            names.append(name)
            sizes.setdefault((rgb.shape[1], rgb.shape[0]), name)
    return SfmInput("video", names, notes={"video": str(path), "fps": config.video_fps,
                                           **_report_selection(selector, "frames", progress)},
                    sizes=sizes)


def _collect_folder(root: Path, images_dir: Path, config: SfmConfig,
                    progress: bool) -> SfmInput:
    paths = sorted(p for p in root.rglob("*") if _is_image_file(p, root))
    if not paths:
        raise InputError(f"{root}: no images ({', '.join(IMAGE_SUFFIXES)}) in this folder, and "
                         "it is not a dataset slamreloc reads")
    selector = _selector(config, "images", None)

    sizes: dict = {}

    def checked():  # (path, RGB), its checked bytes copied (not the path read again)
        for path in _tracked(paths, "copying images" if selector is None
                             else "selecting images", progress):
            data, rgb = checked_image(path)
            name = path.relative_to(root).as_posix()
            size = (rgb.shape[1], rgb.shape[0])
            if sizes and size not in sizes:  # one camera for the folder, as for a dataset
                (w, h), first = next(iter(sizes.items()))
                raise InputError(f"{path}: image is {size[0]}x{size[1]}, the folder's images "
                                 f"are {w}x{h} ({first}); SfM gives a folder one camera")
            sizes.setdefault(size, name)
            (images_dir / name).parent.mkdir(parents=True, exist_ok=True)
            (images_dir / name).write_bytes(data)
            yield path, rgb

    names = [path.relative_to(root).as_posix() for path, _ in
             (checked() if selector is None else selector.select(checked()))]
    for path in [] if selector is None else selector.dropped:
        (images_dir / path.relative_to(root).as_posix()).unlink(missing_ok=True)
    notes = _report_selection(selector, "photos", progress)
    if selector is not None:
        notes["selection"]["not_kept"] = [p.relative_to(root).as_posix()
                                          for p in selector.dropped]
    return SfmInput("images", names, sequential=len(names) > EXHAUSTIVE_UP_TO, notes=notes,
                    sizes=sizes)


def _collect_dataset(dataset, images_dir: Path, config: SfmConfig,
                     progress: bool) -> SfmInput:
    from slamreloc.rgbd import frame_depth

    frames = dataset.frames(config.split)
    if not frames:
        raise InputError(f"{dataset.root}: split '{config.split}' has no frames")
    if config.scale_from_depth and not any(f.depth_path is not None for f in frames):
        raise InputError(f"{dataset.root}: `scale_from_depth` needs depth, and split "
                         f"'{config.split}' has none (give `scale` M instead)")
    selector = _selector(config, "dataset", frames[0].camera)
    if selector is not None:
        from slamreloc.datasets.io import read_frame_image

        listed = _tracked(frames, "selecting images", progress)
        frames = [f for f, _ in selector.select((f, read_frame_image(f)) for f in listed)]
    by_name, sizes = {}, {}
    for frame in _tracked(frames, "copying images", progress):
        named = PurePosixPath(frame.name).suffix.lower() in IMAGE_SUFFIXES
        name = frame.name if named else f"{frame.name}{frame.image_path.suffix.lower()}"
        data, rgb = checked_image(frame.image_path, (frame.camera.width, frame.camera.height))
        sizes.setdefault((rgb.shape[1], rgb.shape[0]), name)
        (images_dir / name).parent.mkdir(parents=True, exist_ok=True)
        (images_dir / name).write_bytes(data)  # the bytes checked, not the path again
        by_name[name] = frame

    def depth_of(name: str) -> np.ndarray | None:
        frame = by_name[name]
        return None if frame.depth_path is None else frame_depth(frame, dataset)

    has_depth = any(f.depth_path is not None for f in frames)
    notes = {"input_dataset": str(dataset.root), "split": config.split, "depth": has_depth,
             **_report_selection(selector, "frames", progress)}
    if selector is not None:
        notes["selection"]["not_kept"] = [f.name for f in selector.dropped]
    return SfmInput("dataset", list(by_name), frames[0].camera,
                    depth_of if has_depth else None, notes=notes, sizes=sizes)


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


def initial_camera(config: SfmConfig, given: Camera | None,
                   sizes: dict | None = None) -> tuple[str, str]:
    """(COLMAP model, comma-separated starting parameters or "" for COLMAP's guess).
    `sizes`: the images' sizes ((width, height) -> an image of that size): a `camera` string
    is scaled to them (`Camera.for_image`: refused for another aspect ratio, or for images of
    several sizes, which one camera cannot describe)."""
    text = config.camera  # as `Camera.parse` takes it everywhere: exact, not stripped
    if text and len(text.split()) == 1:
        model = text
        if model not in MODELS:
            raise InputError(f"`camera`: unknown camera model {text[:40]!r} (known: "
                             f"{', '.join(MODELS)})")
        if given is None:
            return model, ""
        # the dataset's intrinsics, in the asked model (distortion starts at zero)
        head = colmap_head(model, *given.params())
        params = [*head, *([0.0] * (len(PARAMS[model]) - len(head)))]
        return model, ",".join(repr(float(p)) for p in params)
    camera = Camera.parse(text, "`camera`") if text else given
    if camera is None:
        return "SIMPLE_RADIAL", ""
    if text and sizes:
        if len(sizes) > 1:
            (w1, h1), (w2, h2) = list(sizes)[:2]
            raise InputError(f"`camera`: the images have several sizes ({w1}x{h1}: "
                             f"{sizes[(w1, h1)]}, {w2}x{h2}: {sizes[(w2, h2)]}); one camera "
                             "string describes one size")
        (w, h), name = next(iter(sizes.items()))
        camera = camera.for_image(w, h, f"`camera` for {name}")
    return camera.model, ",".join(repr(float(p)) for p in camera.colmap_params())


def _quiet_colmap() -> None:
    import pycolmap

    # fatal lines only: slamreloc shows progress, and says what failed in its own error
    pycolmap.logging.minloglevel = 3


def run_sfm(source: Path, out: Path, config: SfmConfig = SfmConfig(),
            progress: bool = True) -> dict:
    """Run SfM on `source` and write the COLMAP dataset `out`; returns the summary."""
    source, out = Path(source), Path(out)
    if not source.exists():
        raise InputError(f"{source}: not found (a folder of images, a video or a dataset)")
    check_outputs({"`out`": out}, {"the input": source}, folders={"`out`": None})
    video = is_video(source)
    if config.fps is not None and not video:
        raise InputError(f"{source}: `fps` samples a video, and this is not one (leave `fps` "
                         "out)")
    if config.min_parallax is not None and config.select == "auto" and not video:
        raise InputError(f"{source}: `min_parallax` is for `select` parallax, which `select` "
                         "auto uses for a video only (give `select` parallax, or leave "
                         "`min_parallax` out)")
    if video and (problem := frame_name_problem(video_frame_name(source, 0))):
        raise InputError(f"{source}: its frames are named after the video, and "
                         f"{video_frame_name(source, 0)!r} {problem}: rename the video")
    if video or source.is_dir() and not _looks_like_dataset(source):
        # a video or a folder of images: no depth, no camera, no splits
        if config.scale_from_depth:
            raise InputError(f"{source}: `scale_from_depth` needs depth, and a video or a "
                             "folder of images has none (give `scale` M instead)")
        if config.fix_intrinsics and len(config.camera.split()) < 2:
            raise InputError(f"{source}: `fix_intrinsics` needs intrinsics to keep: a `camera` "
                             "string (\"PINHOLE W H fx fy cx cy\"); a video or a folder of "
                             "images has no camera")
        if config.split != SfmConfig.split:
            raise InputError(f"{source}: `split` chooses a dataset's frames; a video or a "
                             "folder of images has none (leave it out)")
    # a second writer fails at once, not late; a full disk names the output; a failed run
    # leaves no folder it made
    from slamreloc.datasets.rosbag import GUESS, camera_in_place_of_info

    # a bag without a calibrated CameraInfo: `camera` gives the model or the intrinsics SfM
    # starts from (a guess of the images' size stands in for the bag's, which is never kept)
    stand_in = GUESS if config.camera.strip() else None
    with folder_write_lock(out, "this dataset", SFM_DEBRIS), naming_output(out), \
            camera_in_place_of_info(stand_in):
        return _run_into(source, out, config, progress)


def _only_sfm_outputs(folder: Path) -> bool:
    """Whether `folder` holds only what an sfm run writes into its temporary folder: `images/`
    and `sparse/` (folders of regular files, nothing linked) and `sfm.json` (or its writer's
    temporaries): a killed run's, removed by the next (`SFM_DEBRIS`)."""
    own = {"images", "sparse"}
    try:
        for entry in os.scandir(folder):
            if entry.name in own:
                if not entry.is_dir(follow_symlinks=False):
                    return False
                for base, dirs, files in os.walk(entry.path):
                    for name in [*dirs, *files]:
                        inside = os.lstat(os.path.join(base, name)).st_mode
                        if not (stat.S_ISDIR(inside) or stat.S_ISREG(inside)):
                            return False
            elif not (entry.name == SFM_JSON and entry.is_file(follow_symlinks=False)
                      or is_file_debris_name(entry.name, Path(SFM_JSON))):
                return False
    except OSError:
        return False
    return True


# sfm never moves a dataset aside: only its temporary is ever debris
SFM_DEBRIS = Debris(new=_only_sfm_outputs, old=None, put_back=None)


def _run_into(source: Path, out: Path, config: SfmConfig, progress: bool) -> dict:
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise InputError(f"{out}: exists and is not empty; choose a new folder")
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = make_temp_dir(temp_dir_path(out), str(out))
    try:
        summary = _run(source, tmp, config, progress)
        still_as_checked(out)  # a link, a file, a pipe put there: said so, not written
        try:  # one rename, over the empty folder given: a kill leaves it or the dataset
            os.replace(tmp, out)
        except OSError as err:
            if err.errno in (errno.ENOTEMPTY, errno.EEXIST):
                raise InputError(f"{out}: something was put into this folder while sfm ran; "
                                 "refusing to replace it (the dataset was not written)") from None
            if err.errno == errno.ENOTDIR:
                raise InputError(f"{out}: became {what_is_there(out)} while sfm ran; the "
                                 "dataset was not written") from None
            raise
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
    if config.overlap is not None and config.matching == "auto" and not inp.sequential:
        raise InputError(f"{source}: `overlap` is for sequential matching, and `matching` auto "
                         "matches these unordered images exhaustively (give `matching` "
                         "sequential, or leave `overlap` out)")
    timings["import_s"] = time.perf_counter() - t0
    model, params = initial_camera(config, inp.camera, inp.sizes)
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
        matches = match_counts(database)
        registered = [] if rec is None else sorted(im.name for im in rec.images.values()
                                                    if im.has_pose)
        share = len(registered) / len(inp.names)
        if len(registered) < 3 or share < config.min_registered:
            try:
                pairs = pair_parallax(database, inp.names)
            except (RuntimeError, ValueError, OSError):  # advice only: the error stands
                pairs = {}
            raise InputError(_failure(source, inp, config, matching, len(registered), pairs))
    unregistered = sorted(set(inp.names) - set(registered))
    scale, scale_note = 1.0, "unknown (SfM units)"
    if config.scale is not None:
        scale, scale_note = config.scale, "metres (user scale)"
    elif config.scale_from_depth:
        if inp.depth_of is None:
            raise InputError(f"{source}: `scale_from_depth` needs depth, and this input has "
                             "none (give `scale` M instead)")
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
        "n_images": len(inp.names), "matches": matches, "n_registered": len(registered),
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


def match_counts(database: Path) -> dict:
    """The matching stage in two numbers: `n_verified_pairs` (image pairs with a verified
    geometry of 15 inlier matches or more) and `n_inlier_matches` (their inlier matches in
    all). Exact matching and seeded verification make both independent of the thread count."""
    import pycolmap

    with pycolmap.Database.open(str(database)) as db:
        counts = [len(g.inlier_matches) for g in db.read_two_view_geometries()[1]]
    verified = [n for n in counts if n >= MIN_PAIR_INLIERS]
    return {"n_verified_pairs": len(verified), "n_inlier_matches": int(sum(verified))}


def pair_parallax(database: Path, names: list[str]) -> dict:
    """What the matched pairs of a SfM database show: `n_pairs` (verified, 15 inliers or more),
    `widest_deg` (the largest `parallax_deg` of their inlier matches over the DIAGNOSED_PAIRS
    pairs furthest apart in `names`' order, with `widest_pair`), and `neighbours_deg` and
    `neighbours_motion` (the median parallax, and the median of the matches' median image
    motion as a share of the longer side, over up to DIAGNOSED_PAIRS pairs of neighbours in that
    order), measured with the database's camera, the mapper's starting one."""
    import pycolmap

    with pycolmap.Database.open(str(database)) as db:
        cameras = {c.camera_id: c for c in db.read_all_cameras()}
        images = {im.image_id: im for im in db.read_all_images()}
        order = {name: i for i, name in enumerate(names)}
        pairs = []
        for pair_id, geometry in zip(*db.read_two_view_geometries()):
            if len(geometry.inlier_matches) >= MIN_PAIR_INLIERS:
                a, b = (images[i] for i in pycolmap.pair_id_to_image_pair(pair_id))
                pairs.append((abs(order.get(a.name, 0) - order.get(b.name, 0)), a, b,
                              geometry.inlier_matches))
        out = {"n_pairs": len(pairs)}
        if not pairs:
            return out
        pairs.sort(key=lambda p: p[0])
        measured = {}

        def measure(pair) -> tuple[float | None, float]:  # parallax, image motion
            _, a, b, matches = pair
            if (a.name, b.name) not in measured:
                pixels = [db.read_keypoints(im.image_id)[matches[:, k], :2].astype(np.float64)
                          for k, im in enumerate((a, b))]
                camera = cameras[a.camera_id]
                motion = np.median(np.linalg.norm(pixels[1] - pixels[0], axis=1))
                measured[a.name, b.name] = (
                    parallax_deg(*(cameras[im.camera_id].cam_from_img(x)
                                   for im, x in zip((a, b), pixels)),
                                 camera.mean_focal_length()),
                    float(motion / max(camera.width, camera.height)))
            return measured[a.name, b.name]

        widest = [(measure(p)[0], p[1].name, p[2].name) for p in pairs[-DIAGNOSED_PAIRS:]]
        widest = [w for w in widest if w[0] is not None]
        neighbours = [measure(p) for p in pairs[:DIAGNOSED_PAIRS] if p[0] == 1]
        neighbours = [n for n in neighbours if n[0] is not None]
    if widest:
        angle, a, b = max(widest)
        out.update(widest_deg=angle, widest_pair=[a, b])
    if neighbours:
        out["neighbours_deg"] = float(np.median([n[0] for n in neighbours]))
        out["neighbours_motion"] = float(np.median([n[1] for n in neighbours]))
    return out


def _failure(source: Path, inp: SfmInput, config: SfmConfig, matching: str, n_registered: int,
             pairs: dict) -> str:
    """The one-line error of a run that registered too few images: the numbers, the cause the
    matched pairs show (`pair_parallax`), and advice that fits it, never an option already in
    use."""
    n = len(inp.names)
    need = (f"at least {100 * config.min_registered:.0f} % needed"
            if n_registered / n < config.min_registered else "at least 3 needed")
    head = (f"{source}: SfM registered only {n_registered} of {n} images "
            f"({100 * n_registered / n:.0f} %, {need})")
    what = "frames" if inp.kind == "video" else "photos"
    selected = "selection" in inp.notes
    widest, neighbours = pairs.get("widest_deg"), pairs.get("neighbours_deg")
    # near-duplicates: what selection drops (and would have, had it been asked for)
    duplicates = (not selected and neighbours is not None and neighbours < config.parallax_deg
                  and pairs["neighbours_motion"] < MIN_MOTION)
    if widest is not None and (widest < PARALLAX_START_DEG or duplicates):
        near = "" if neighbours is None else f", neighbouring ones at {neighbours:.2f} deg"
        cause = (f"too little parallax between the {what}: the camera moved too little between "
                 f"them (the widest matched pair sees its points at a median {widest:.1f} deg"
                 f"{near}; COLMAP's mapper needs about {PARALLAX_START_DEG:g} deg to start a "
                 "model)")
        advice = ["move the camera more between the first and the last view (steps sideways "
                  "or around the scene, not only turning)"]
        if duplicates:
            advice.insert(0, f"keep fewer, more spread-out {what} (`select` parallax keeps one "
                             f"once it has {config.parallax_deg:g} deg of parallax to the last "
                             "one kept)")
        return f"{head}: {cause}; {_either(advice)}"
    matched = pairs.get("n_pairs") != 0  # unknown where the pairs could not be read
    cause = "" if matched else (": no two images share enough verified matches (too little "
                                "overlap or texture)")
    advice = []
    if matching == "sequential":
        advice.append("`matching` exhaustive")
    if not config.camera.strip():
        advice.append("a camera model that fits the lens (`camera` OPENCV or OPENCV_FISHEYE)")
    if inp.kind == "video":
        advice.append(f"more overlap (a higher `fps` than {config.video_fps:g})")
    elif not matched:
        advice.append(f"{what} that overlap more")
    if matching == "sequential":
        advice.append(f"a higher `overlap` than {config.sequential_overlap}")
    if config.min_registered > 0 and n_registered >= 3:
        advice.append("a lower `min_registered`")
    return f"{head}{cause}" + (f"; try {_either(advice)}" if advice else "")


def _either(items: list[str]) -> str:
    return items[0] if len(items) == 1 else f"{', '.join(items[:-1])}, or {items[-1]}"


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
            pairing.overlap = config.sequential_overlap
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
                         "`scale_from_depth` needs depth registered to the images")
    ratios = np.asarray(ratios)
    q1, med, q3 = np.percentile(ratios, [25, 50, 75])
    return float(med), float((q3 - q1) / 2 / med), len(ratios)


def print_sfm_summary(s: dict) -> None:
    unreg = s["unregistered"]
    listed = ", ".join(unreg[:5]) + (f", ... ({len(unreg)} in {s['dataset']}/{SFM_JSON})"
                                     if len(unreg) > 5 else "")
    sel = s.get("selection")
    kept = (f" (kept by parallax from {sel['n_candidates']})" if sel else "")
    console.print(
        f"[green]SfM dataset written[/green] to {shown(s['dataset'])}: {s['n_registered']}/"
        f"{s['n_images']} images{kept} registered, {s['n_points']} points, mean track length "
        f"{s['mean_track_length']:.1f}, mean reprojection error "
        f"{s['mean_reprojection_error_px']:.2f} px, units {s['units']}, camera {s['camera']}, "
        f"{s['timings_s']['total_s']:.0f} s")
    if unreg:
        console.print(f"[yellow]not registered[/yellow]: {shown(listed)}")
