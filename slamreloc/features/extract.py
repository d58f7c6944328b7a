"""Feature extraction over many frames (two worker threads; OpenCV and torch release the GIL);
keypoints come out in each frame's pinhole pixels (undistorted)."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

from slamreloc.datasets import read_frame_image
from slamreloc.features import Extractor
from slamreloc.io.images import picture_digest
from slamreloc.runtime.progress import track
from slamreloc.types import Features, Frame


def extract_frames(frames: list[Frame], extractor: Extractor, progress: bool = True,
                   workers: int = 2) -> list[Features]:
    """Each frame's features."""
    return extract_with_pictures(frames, extractor, progress, workers, pictures=False)[0]


def extract_with_pictures(frames: list[Frame], extractor: Extractor, progress: bool = True,
                          workers: int = 2, pictures: bool = True
                          ) -> tuple[list[Features], list[str]]:
    """Each frame's features, and its picture (`io.images.picture_digest` of the pixels
    extracted from; none where `pictures` is False): what a map records of the frames it
    holds (`map.joining`)."""
    extractor.check_frames(frames)

    def one(frame: Frame) -> tuple[Features, str]:
        image = read_frame_image(frame)
        return extractor.extract(image, frame.camera), picture_digest(image) if pictures else ""

    with ThreadPoolExecutor(workers) as pool:
        results = list(track(pool.map(one, frames), "extracting features", total=len(frames),
                             enabled=progress))
    return [f for f, _ in results], [p for _, p in results if pictures]
