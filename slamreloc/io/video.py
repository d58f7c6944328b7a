"""Frames of a video file, sampled at a given rate, for `slamreloc sfm`."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np

from slamreloc.errors import InputError
from slamreloc.io.images import check_image_size

VIDEO_SUFFIXES = (".mp4", ".mov", ".avi", ".mkv", ".webm", ".m4v", ".mpg", ".mpeg", ".wmv")


def is_video(path: Path) -> bool:
    return Path(path).is_file() and Path(path).suffix.lower() in VIDEO_SUFFIXES


def video_frames(path: Path, fps: float) -> Iterator[tuple[float, np.ndarray]]:
    """(timestamp in seconds, RGB uint8 image) of every frame nearest a multiple of 1/fps.
    One-line InputError for a file that cannot be opened (raised here, before any frame) or
    decoded, or whose frames break the image bounds (`slamreloc.io.limits`)."""
    import cv2

    path = Path(path)
    if not fps > 0:
        raise InputError(f"`fps` must be positive, got {fps}")
    from slamreloc.io.fileio import open_regular

    with open_regular(path, "video"):  # a pipe or a device would block the decoder
        pass
    try:
        str(path).encode("utf-8")
    except UnicodeEncodeError:  # OpenCV's binding cannot take such a path (it crashed)
        raise InputError(f"{path}: its path is not UTF-8 text, which OpenCV's video reader "
                         "cannot open; rename the video (or its folder)") from None
    cap = cv2.VideoCapture(str(path), cv2.CAP_FFMPEG)
    if not cap.isOpened():
        cap.release()
        raise InputError(f"{path}: not a video OpenCV's FFmpeg can open")
    try:
        check_image_size(int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)),
                         int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)), path)
    except InputError:
        cap.release()
        raise
    return _sampled(cap, path, fps)


def _sampled(cap, path: Path, fps: float) -> Iterator[tuple[float, np.ndarray]]:
    import cv2

    try:
        rate = cap.get(cv2.CAP_PROP_FPS)
        rate = rate if 0 < rate < 1000 else 30.0
        step, next_t, index, n_out = 1.0 / fps, 0.0, 0, 0
        while True:
            ok = cap.grab()
            if not ok:
                break
            t = index / rate
            index += 1
            if t + 0.5 / rate < next_t:
                continue
            ok, bgr = cap.retrieve()
            if not ok or bgr is None:
                raise InputError(f"{path}: frame {index - 1} cannot be decoded")
            next_t += step
            n_out += 1
            yield t, np.ascontiguousarray(bgr[:, :, ::-1])
        if n_out == 0:
            raise InputError(f"{path}: no frame could be decoded (not a video, or a codec "
                             "OpenCV's FFmpeg lacks)")
        declared = cap.get(cv2.CAP_PROP_FRAME_COUNT)  # the header's (or the container's
        if 0 < declared < 1e9 and index < declared - max(2, 0.1 * declared):  # estimate)
            raise InputError(f"{path}: only {index} of the {int(declared)} frames its header "
                             "declares could be read: the file is cut short or damaged")
    finally:
        cap.release()
