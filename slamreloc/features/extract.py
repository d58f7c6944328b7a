"""Feature extraction over many frames (two worker threads; OpenCV and torch release the GIL);
keypoints come out in each frame's pinhole pixels (undistorted)."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

from slamreloc.datasets import read_frame_image
from slamreloc.features import Extractor
from slamreloc.runtime.progress import track
from slamreloc.types import Features, Frame


def extract_frames(frames: list[Frame], extractor: Extractor, progress: bool = True,
                   workers: int = 2) -> list[Features]:
    extractor.check_frames(frames)
    with ThreadPoolExecutor(workers) as pool:
        results = pool.map(lambda f: extractor.extract(read_frame_image(f), f.camera),
                           frames)
        return list(track(results, "extracting features", total=len(frames), enabled=progress))
