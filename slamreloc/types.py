"""Typed records passed between pipeline stages (frames in pixels and metres)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from slamreloc import camera_models as lens
from slamreloc.errors import InputError
from slamreloc.geometry import Rigid3


@dataclass(frozen=True)
class Camera:
    """Intrinsics in pixels, OpenCV convention (pixel centres at integer coordinates), and a
    lens model: PINHOLE, or one of COLMAP's distortion models with its parameters
    (`slamreloc.camera_models`). Keypoints of a distorted camera are undistorted into its
    pinhole camera (same fx, fy, cx, cy) at extraction; `K` and `to_pycolmap` are that
    pinhole camera's."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    model: str = "PINHOLE"
    distortion: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        object.__setattr__(self, "distortion", tuple(float(v) if isinstance(v, (int, float))
                                                     and not isinstance(v, bool) else v
                                                     for v in self.distortion))
        problem = lens_camera_problem(self.model, self.width, self.height, self.fx, self.fy,
                                      self.cx, self.cy, self.distortion)
        if problem:
            raise InputError(f"invalid camera: {problem}")
        if self.model != "OPENCV_FISHEYE" and not any(self.distortion):  # one name per lens
            object.__setattr__(self, "model", "PINHOLE")
            object.__setattr__(self, "distortion", ())

    @classmethod
    def from_colmap(cls, model: str, width: int, height: int, params, source: str) -> Camera:
        """From a COLMAP model name and parameter list (COLMAP's principal point); an
        InputError naming `source` for anything out of range."""
        model, fx, fy, cx, cy, distortion = lens.colmap_values(model, params, source)
        problem = lens_camera_problem(model, width, height, fx, fy, cx, cy, distortion)
        if problem:  # named by `source` here, not as "invalid camera"
            # said with the principal point as given (COLMAP's, half a pixel off ours) where
            # that is what is wrong, so the message quotes the number the user wrote
            given = lens_camera_problem(model, width, height, fx, fy, cx + 0.5, cy + 0.5,
                                        distortion)
            raise InputError(f"{source}: {given or problem}")
        return cls(width, height, fx, fy, cx, cy, model, distortion)

    @classmethod
    def parse(cls, text: str, source: str = "`camera`") -> Camera:
        """A COLMAP camera string, `"OPENCV 640 480 fx fy cx cy k1 k2 p1 p2"`, or a line of
        cameras.txt (principal point in COLMAP's convention). Every number is a plain ASCII
        decimal (`slamreloc.io.numbers`: no digit separators, no other scripts' digits)."""
        model, width, height, params = lens.split_camera_string(text, source)
        return cls.from_colmap(model, width, height, params, source)

    def same_as(self, other: Camera) -> bool:
        """The same camera: lens model, width and height equal, every parameter (fx, fy, cx,
        cy, distortion) within SAME_CAMERA_RTOL of the other's (absolutely 1e-9 near zero).
        The one rule wherever two cameras must be one (a map's frames, a bag's CameraInfo)."""
        if (self.model, self.width, self.height) != (other.model, other.width, other.height):
            return False
        a, b = [*self.params(), *self.distortion], [*other.params(), *other.distortion]
        return len(a) == len(b) and all(math.isclose(x, y, rel_tol=SAME_CAMERA_RTOL,
                                                     abs_tol=1e-9) for x, y in zip(a, b))

    def describe(self) -> str:
        """`PINHOLE 320x240 (fx 262.5, fy 262.5, cx 159.5, cy 119.5)`, distortion after: as
        precise as `same_as` tells cameras apart (10 significant digits)."""
        text = (f"{self.model} {self.width}x{self.height} (fx {self.fx:.10g}, fy "
                f"{self.fy:.10g}, cx {self.cx:.10g}, cy {self.cy:.10g}")
        if self.distortion:
            text += ", distortion " + " ".join(f"{d:.10g}" for d in self.distortion)
        return text + ")"

    def colmap_params(self) -> list[float]:
        """The parameters of `self.model` in COLMAP's convention (cameras.txt)."""
        return [*lens.colmap_head(self.model, self.fx, self.fy, self.cx, self.cy),
                *self.distortion]

    def colmap_string(self) -> str:
        """The COLMAP camera string `Camera.parse` reads back."""
        return " ".join([self.model, str(self.width), str(self.height),
                         *(repr(float(p)) for p in self.colmap_params())])

    @property
    def distorted(self) -> bool:
        return self.model != "PINHOLE"

    @property
    def pinhole(self) -> Camera:
        """The pinhole camera keypoints are undistorted into (this camera if undistorted)."""
        return Camera(self.width, self.height, self.fx, self.fy, self.cx, self.cy)

    def undistort(self, uv: np.ndarray) -> np.ndarray:
        """(N, 2) image pixels -> pinhole pixels (unchanged for a pinhole camera)."""
        return lens.map_pixels(uv, *self.params(), self.model, self.distortion, True)

    def distort(self, uv: np.ndarray) -> np.ndarray:
        """(N, 2) pinhole pixels -> image pixels (unchanged for a pinhole camera)."""
        return lens.map_pixels(uv, *self.params(), self.model, self.distortion, False)

    def undistort_image(self, image: np.ndarray) -> np.ndarray:
        """An image of this camera (any size: the camera is scaled to it) resampled onto its
        pinhole camera's pixel grid by nearest neighbour (for depth maps, whose values must
        not be blended); unchanged for a pinhole camera."""
        import cv2

        if not self.distorted:
            return image
        h, w = image.shape[:2]
        cam = self.scaled_to(w, h)
        maps = lens.pinhole_grid_sources(w, h, *cam.params(), cam.model, cam.distortion)
        return cv2.remap(image, maps, None, cv2.INTER_NEAREST,
                         borderMode=cv2.BORDER_CONSTANT, borderValue=0)

    @property
    def K(self) -> np.ndarray:  # noqa: N802 - the usual name
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1.0]])

    def params(self) -> list[float]:
        return [self.fx, self.fy, self.cx, self.cy]

    def for_image(self, width: int, height: int, source: str = "camera") -> Camera:
        """This camera for an image of width x height: scaled to it (`scaled_to`) when the
        image has the camera's aspect ratio (within ASPECT_TOL, what rounding a resized image's
        sides gives), else InputError naming `source`: a camera of another aspect ratio is
        never stretched onto an image. The one rule wherever a camera meets an image
        (`localize`'s cameras, `sfm --camera`, the service's query cameras)."""
        problem = aspect_problem(self.width, self.height, width, height)
        if problem:
            raise InputError(f"{source}: {problem}")
        return self.scaled_to(width, height)

    def scaled_to(self, width: int, height: int) -> Camera:
        """The intrinsics scaled by the size ratio, each axis on its own (no check: a camera
        applied to an image goes through `for_image`)."""
        sx, sy = width / self.width, height / self.height
        return Camera(width, height, self.fx * sx, self.fy * sy, self.cx * sx, self.cy * sy,
                      self.model, self.distortion)

    def to_pycolmap(self):
        """The pinhole camera (undistorted keypoints) as a pycolmap camera."""
        import pycolmap

        return pycolmap.Camera(model="PINHOLE", width=self.width, height=self.height,
                               params=self.params())

    def to_dict(self) -> dict:
        d = {"width": self.width, "height": self.height, "fx": self.fx, "fy": self.fy,
             "cx": self.cx, "cy": self.cy}
        if self.distorted:
            d.update(model=self.model, distortion=list(self.distortion))
        return d

    @classmethod
    def from_dict(cls, d: dict) -> Camera:
        return cls(**{**d, "distortion": tuple(d.get("distortion", ()))})


ASPECT_TOL = 0.01  # relative difference of the two sides' scales
SAME_CAMERA_RTOL = 1e-6  # `Camera.same_as`: what a camera written as text and read back keeps


def aspect_problem(cam_width: int, cam_height: int, width: int, height: int) -> str | None:
    """Why a camera of cam_width x cam_height cannot describe an image of width x height (None
    when it can: the same aspect ratio within ASPECT_TOL, any size)."""
    sx, sy = width / cam_width, height / cam_height
    if abs(sx - sy) <= ASPECT_TOL * max(sx, sy):
        return None
    return (f"the camera is {cam_width}x{cam_height} and the image {width}x{height}: another "
            "aspect ratio (a camera is scaled to an image of its aspect ratio, never "
            "stretched)")


MAX_INTRINSIC = 1e7  # pixels: beyond any real camera (a 65536-pixel image at 0.4 degrees)


def _show(v) -> str:
    """A value for an error message, short: numbers as `:g` (1e+300, never 301 digits; an
    integer beyond float range by its leading digits and exponent), others by repr."""
    if isinstance(v, bool) or not isinstance(v, (int, float, np.number)):
        return repr(v)[:40]
    if isinstance(v, (int, np.integer)) and abs(int(v)) >= 10 ** 16:
        digits = str(abs(int(v)))
        return f"{'-' if v < 0 else ''}{digits[0]}.{digits[1:4]}e+{len(digits) - 1}"
    return f"{float(v):g}"


def camera_problem(width, height, fx, fy, cx, cy) -> str | None:
    """What is wrong with pinhole intrinsics (None when nothing): sizes whole numbers in
    1..65536, fx and fy in [1, 1e7] pixels, cx and cy finite within +-1e7 pixels (a camera
    of a known size also `centre_problem`)."""
    for name, v in (("width", width), ("height", height)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or not 0 < v <= 1 << 16:
            return f"{name} must be a whole number of pixels in 1..65536, got {_show(v)}"
    for name, v in (("fx", fx), ("fy", fy), ("cx", cx), ("cy", cy)):
        if isinstance(v, bool) or not isinstance(v, (int, float, np.number)) or \
                not abs(float(v)) <= MAX_INTRINSIC:  # False for NaN
            return (f"{name} must be a finite number within +-{MAX_INTRINSIC:g} pixels, got "
                    f"{_show(v)}")
    if fx < 1 or fy < 1:
        return (f"focal lengths must be positive (at least 1 pixel), got fx={_show(fx)}, "
                f"fy={_show(fy)}")
    return None


def centre_problem(width: int, height: int, cx: float, cy: float) -> str | None:
    """What is wrong with a principal point for an image of width x height (None when
    nothing): it lies within one image size of the image (cx in [-width, 2 width], cy
    likewise); a crop moves it off centre, never a whole image away."""
    for name, v, size in (("cx", cx, width), ("cy", cy, height)):
        if not -size <= v <= 2 * size:
            return (f"{name} must lie within one image size of the image ({-size}..{2 * size} "
                    f"pixels for {size}), got {_show(v)}")
    return None


def k_matrix_problem(k) -> str | None:
    """What is wrong with a 3x3 pinhole matrix K, or its 9 values row by row (None when
    nothing): finite, [[fx 0 cx]
    [0 fy cy] [0 0 1]]: a skew or another last row would be silently ignored. The one rule
    of intrinsics files and ROS CameraInfo messages."""
    k = np.asarray(k, np.float64)
    if k.size != 9:
        return f"K must be 3x3, got {k.size} values"
    k = k.reshape(3, 3)  # its 9 values row by row, as CameraInfo sends them
    if not np.all(np.isfinite(k)):
        return "K must be finite numbers"
    if not np.any(k):  # ROS's CameraInfo of a camera not calibrated yet
        return "K is all zero, which says the camera is not calibrated"
    if k[0, 1] != 0 or k[1, 0] != 0 or list(k[2]) != [0.0, 0.0, 1.0]:
        return "K must be [[fx 0 cx] [0 fy cy] [0 0 1]] (no skew)"
    return None


def lens_camera_problem(model: str, width, height, fx, fy, cx, cy, distortion) -> str | None:
    """Every rule of a camera, in order (None when it keeps them all): `camera_problem`,
    `centre_problem`, the lens model's distortion ranges and `fold_problem` (the image must
    not fold inside it). The one check of `Camera` and `Camera.from_colmap`."""
    return (camera_problem(width, height, fx, fy, cx, cy)
            or centre_problem(width, height, cx, cy)
            or lens.distortion_problem(model, distortion)
            or lens.fold_problem(model, distortion, width, height, fx, fy, cx, cy))


def frame_name_problem(name: str) -> str | None:
    """Why `name` cannot name a map's training frame (None when it can): a frame is named by
    its image's path relative to the dataset root (`seq-01/frame-000000`), which export writes
    into lines (a COLMAP images.txt, a TUM names sidecar) and the viewer looks up in the
    dataset: non-empty, without line breaks or other control characters (a space, as photos'
    names have, is kept), relative, never leaving the root (`..`), and in one spelling only
    (no empty or `.` part), so that a name compares equal to the dataset's own."""
    if not name:
        return "is empty"
    if any(not c.isprintable() and c != " " for c in name):  # photos' names hold spaces
        return "holds a line break or another control character"
    parts = name.replace("\\", "/").split("/")
    if name.startswith("/") or ".." in parts:
        return "is not a path inside the dataset (absolute, or with '..')"
    if "" in parts or "." in parts:  # one file, one name: `a/./b` and `a//b` are `a/b`
        return "is not a plain relative path (an empty or '.' part, as in 'a//b' or 'a/./b')"
    return None


@dataclass
class Frame:
    """One image of a dataset. `world_from_cam` (metres, the map/dataset frame from the RGB
    camera's OpenCV frame) is None when the frame has no ground truth.

    Depth (`depth_path`, None without) is either registered to the image (same pixels as
    `camera`: `depth_camera` and `rgb_from_depth` are None) or taken by a camera of its own:
    then `depth_camera` is that camera, pinhole, in pixels of the depth map's own size
    (7-Scenes: fx = fy = 585, cx = 320, cy = 240 at 640x480; a camera given at another size is
    scaled to the depth map where it is used) and `rgb_from_depth` its pose in the RGB
    camera's frame (metres; the rig calibration, 7-Scenes' Kinect v1: 2.6 cm along x,
    0.6 deg)."""

    name: str  # unique inside its dataset, e.g. "seq-01/frame-000000"
    image_path: Path
    camera: Camera
    depth_path: Path | None = None
    world_from_cam: Rigid3 | None = None
    sequence: str = ""
    timestamp: float = 0.0  # seconds
    depth_camera: Camera | None = None  # None: depth registered to `camera`, or no depth
    rgb_from_depth: Rigid3 | None = None  # None: registered (identity), or no depth


@dataclass
class Features:
    """Local features of one image: keypoints in pixels, L2-normalised float32 descriptors."""

    keypoints: np.ndarray  # (N, 2) float32, x right / y down
    descriptors: np.ndarray  # (N, D) float32
    scores: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32))  # (N,)

    def __len__(self) -> int:
        return len(self.keypoints)

    def subset(self, idx: np.ndarray) -> Features:
        scores = self.scores[idx] if len(self.scores) else self.scores
        return Features(self.keypoints[idx], self.descriptors[idx], scores)
