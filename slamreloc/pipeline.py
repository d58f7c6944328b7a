"""Entry functions behind the CLI: evaluate a map on a dataset, localize loose images."""

from __future__ import annotations

from pathlib import Path

from slamreloc.datasets import Dataset, load_dataset, read_image
from slamreloc.errors import InputError
from slamreloc.evaluate import evaluate_frames, summarize, write_tum
from slamreloc.fileio import check_outputs, write_json
from slamreloc.geometry import Rigid3, tum_line
from slamreloc.localizer import make_localizer
from slamreloc.map_format import check_is_map
from slamreloc.scene_map import SceneMap
from slamreloc.surface import frame_cloud, refine_pose
from slamreloc.types import Camera, Frame, camera_problem


def depth_refiner(scene_map: SceneMap, dataset: Dataset):
    """`(frame, world_from_cam) -> world_from_cam`: ICP of the frame's depth against the map's
    surface (the PnP pose where the fit is not accepted)."""
    surface = scene_map.surface
    if surface is None:
        raise InputError(f"{scene_map.root}: map has no surface (it was built without depth); "
                         "--depth needs one")

    def refine(frame: Frame, world_from_cam: Rigid3) -> Rigid3:
        return refine_pose(surface, frame_cloud(frame, dataset), world_from_cam).chosen()

    return refine


def evaluate_method(scene_map: SceneMap, dataset_dir: Path, split: str = "test",
                    method: str = "regressor", device: str = "cpu", progress: bool = True,
                    depth: bool = False):
    """Localize a split with one method (`depth`: refine each pose by ICP of the frame's depth
    against the map's surface). Returns (report dict, per-query results, frames)."""
    dataset = load_dataset(dataset_dir)
    frames = dataset.frames(split)
    if not frames:
        raise InputError(f"{dataset_dir}: split '{split}' has no frames to evaluate")
    refine = depth_refiner(scene_map, dataset) if depth else None
    localizer = make_localizer(scene_map, method, device=device)
    results = evaluate_frames(localizer, frames, progress, refine)
    summary = summarize(results, method)
    summary["refine"] = "depth" if depth else None
    summary["map"] = {"parameters": scene_map.regressor.num_parameters(),
                      "size_bytes": scene_map.size_bytes(),
                      "database_bytes": scene_map.database_bytes(),
                      "n_database_descriptors": scene_map.info.n_labelled}
    summary["device"] = localizer.device.type
    summary["dataset"] = {"root": str(Path(dataset_dir).resolve()), "split": split}
    summary["per_query"] = [
        {"name": r.name, "translation_error_m": r.translation_error_m if r.world_from_cam else None,
         "rotation_error_deg": r.rotation_error_deg if r.world_from_cam else None,
         "num_inliers": r.num_inliers} for r in results]
    return summary, results, frames


def run_evaluation(map_dir: Path, dataset_dir: Path, report: Path, split: str = "test",
                   method: str = "regressor", poses: Path | None = None,
                   plot: Path | None = None, device: str = "cpu", progress: bool = True,
                   depth: bool = False) -> dict:
    """Localize a split, write REPORT.json (and TUM poses / a plot); returns the report."""
    check_is_map(map_dir)  # what the inputs are, then where the outputs may go
    check_outputs({"--report": report, "--poses": poses, "--plot": plot},
                  {"the map": map_dir, "the dataset": dataset_dir})
    summary, results, frames = evaluate_method(SceneMap.load(map_dir), dataset_dir, split,
                                               method, device, progress, depth)
    write_json(report, summary)
    if poses:
        write_tum(poses, results)
    if plot:
        from slamreloc.plots import plot_evaluation

        plot_evaluation(plot, {method: results}, frames)
    return summary


def localize_images(map_dir: Path, images: list[Path],
                    intrinsics: Camera | tuple[float, float, float, float] | None = None,
                    method: str = "regressor"):
    """Yield (line, status) per image (or per frame of a ROS bag among `images`): a TUM line
    plus inlier count ("ok"), `# name: not localized` ("failed"), or `error: ...` for an
    image that cannot be read or is out of bounds ("error"). `intrinsics`: a Camera (any lens
    model, scaled to each image), pinhole (fx, fy, cx, cy) in pixels, else the bag's camera
    or the map's, scaled to each image."""
    if intrinsics is not None and not isinstance(intrinsics, Camera):
        problem = camera_problem(1, 1, *intrinsics)
        if problem:
            raise InputError(f"--intrinsics: {problem}")
    scene_map = SceneMap.load(map_dir)
    localizer = make_localizer(scene_map, method)
    for name, path, own_camera in _query_images(images):
        try:
            # the bounds, the extractor's included, are checked before anything is decoded
            image = read_image(path, fits=localizer.extractor.check_size)
        except InputError as err:
            yield f"error: {err}", "error"
            continue
        h, w = image.shape[:2]
        if isinstance(intrinsics, Camera):
            camera = intrinsics.scaled_to(w, h)
        elif intrinsics:
            camera = Camera(w, h, *intrinsics)
        else:
            camera = (own_camera or scene_map.camera).scaled_to(w, h)
        loc = localizer.localize(image, camera)
        est = loc.estimate
        if est.success:
            yield f"{tum_line(name, est.world_from_cam)} {est.num_inliers}", "ok"
        else:
            yield f"# {name}: not localized ({est.num_inliers} inliers)", "failed"


def _query_images(paths: list[Path]):
    """(name, image file, its camera or None) of each image file, and of each frame of a ROS
    bag among them (named by frame, with the bag's camera)."""
    from slamreloc.datasets.rosbag import is_rosbag, load_rosbag

    for path in paths:
        if is_rosbag(Path(path)):
            for frame in load_rosbag(Path(path)).frames("all"):
                yield frame.name, frame.image_path, frame.camera
        else:
            yield Path(path).name, path, None
