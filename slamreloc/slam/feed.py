"""Feeding a dataset's frames to `SlamBackend`: read what the backend needs of each frame (the
RGB image, the depth map) and step the backend, one frame at a time.

Depth is handed over as stored, in metres in the depth camera's pixels, with that camera
(`Frame.depth_camera`, None when depth is registered to the image): the odometry front ends and
the relocalization plugin place it with that camera, so nothing is warped here.
"""

from __future__ import annotations

import time
from collections.abc import Iterable, Iterator
from dataclasses import dataclass

import numpy as np

from slamreloc.datasets import Dataset, read_frame_depth, read_frame_image
from slamreloc.errors import InputError
from slamreloc.geometry import Rigid3
from slamreloc.slam.backend import SlamBackend, StepResult
from slamreloc.types import Camera, Frame


@dataclass(frozen=True)
class FrameInput:
    """One frame as `SlamBackend.process` takes it: RGB uint8 (or None), depth in metres in the
    depth camera's pixels (or None), the RGB camera, the timestamp (seconds), for a backend
    without an odometry front end the frame's pose in your odometry frame, and the depth's
    own camera where it is not registered to the image (`Frame.depth_camera`, placed by
    `Frame.rgb_from_depth`), and the frame's name."""

    camera: Camera
    timestamp: float
    image: np.ndarray | None = None
    depth: np.ndarray | None = None
    odometry_world_from_cam: Rigid3 | None = None
    depth_camera: Camera | None = None
    rgb_from_depth: Rigid3 | None = None
    name: str | None = None


@dataclass(frozen=True)
class FedFrame:
    """The backend's result for one frame and the seconds `process` took (reading excluded)."""

    result: StepResult
    backend_s: float


def read_frames(dataset: Dataset, frames: Iterable[Frame], image: bool = True,
                depth: bool = True) -> Iterator[FrameInput]:
    """Each frame's inputs, read lazily: the image if `image` (relocalization plugins, open3d's
    hybrid odometry), the depth if `depth` (depth odometry; InputError for a frame without)."""
    for frame in frames:
        if depth and frame.depth_path is None:
            raise InputError(f"{frame.image_path}: no depth image for depth odometry")
        yield FrameInput(
            frame.camera, frame.timestamp,
            read_frame_image(frame) if image else None,
            read_frame_depth(frame, dataset.depth_units_per_metre) if depth else None,
            depth_camera=frame.depth_camera, rgb_from_depth=frame.rgb_from_depth,
            name=frame.name)


def depth_camera_of(frames: Iterable[Frame]) -> Camera | None:
    """The one depth camera of the frames with depth (`Frame.depth_camera`; None: registered
    to the image), for an odometry front end configured once for a run; InputError where
    frames of the run have different ones."""
    cameras = {f.depth_camera for f in frames if f.depth_path is not None}
    if len(cameras) > 1:
        raise InputError(f"{len(cameras)} different depth cameras among the frames: one "
                         "odometry run takes one")
    return next(iter(cameras), None)


def feed(backend: SlamBackend, inputs: Iterable[FrameInput]) -> Iterator[FedFrame]:
    """Step `backend` with each input, in order, yielding each result as it is processed."""
    for inp in inputs:
        t0 = time.perf_counter()
        result = backend.process(inp.image, inp.depth, inp.camera, inp.odometry_world_from_cam,
                                 inp.timestamp, inp.depth_camera, inp.rgb_from_depth,
                                 inp.name)
        yield FedFrame(result, time.perf_counter() - t0)


def feed_all(backend: SlamBackend, inputs: Iterable[FrameInput]) -> float:
    """Step `backend` with every input; returns the seconds spent in `process`."""
    return sum(fed.backend_s for fed in feed(backend, inputs))
