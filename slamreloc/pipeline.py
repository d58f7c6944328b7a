"""Entry functions behind the CLI: evaluate a map on a dataset, localize loose images."""

from __future__ import annotations

from pathlib import Path

from slamreloc.datasets import load_dataset, read_image
from slamreloc.errors import InputError
from slamreloc.evaluate import evaluate_frames, summarize, write_json, write_tum
from slamreloc.geometry import tum_line
from slamreloc.localizer import make_localizer
from slamreloc.scene_map import SceneMap
from slamreloc.types import Camera


def evaluate_method(scene_map: SceneMap, dataset_dir: Path, split: str = "test",
                    method: str = "regressor", device: str = "cpu", progress: bool = True):
    """Localize a split with one method. Returns (report dict, per-query results, frames)."""
    frames = load_dataset(dataset_dir).frames(split)
    if not frames:
        raise InputError(f"{dataset_dir}: split '{split}' has no frames to evaluate")
    localizer = make_localizer(scene_map, method, device=device)
    results = evaluate_frames(localizer, frames, progress)
    summary = summarize(results, method)
    summary["map"] = {"parameters": scene_map.regressor.num_parameters(),
                      "size_bytes": scene_map.size_bytes(),
                      "database_bytes": scene_map.database_bytes(),
                      "n_database_descriptors": int(scene_map.meta["labels"]["n_labelled"])}
    summary["device"] = localizer.device.type
    summary["dataset"] = {"root": str(Path(dataset_dir).resolve()), "split": split}
    summary["per_query"] = [
        {"name": r.name, "translation_error_m": r.translation_error_m if r.world_from_cam else None,
         "rotation_error_deg": r.rotation_error_deg if r.world_from_cam else None,
         "num_inliers": r.num_inliers} for r in results]
    return summary, results, frames


def run_evaluation(map_dir: Path, dataset_dir: Path, report: Path, split: str = "test",
                   method: str = "regressor", poses: Path | None = None,
                   plot: Path | None = None, device: str = "cpu", progress: bool = True) -> dict:
    """Localize a split, write REPORT.json (and TUM poses / a plot); returns the report."""
    summary, results, frames = evaluate_method(SceneMap.load(map_dir), dataset_dir, split,
                                               method, device, progress)
    write_json(report, summary)
    if poses:
        write_tum(poses, results)
    if plot:
        from slamreloc.plots import plot_evaluation

        plot_evaluation(plot, {method: results}, frames)
    return summary


def localize_images(map_dir: Path, images: list[Path], intrinsics=None,
                    method: str = "regressor"):
    """Yield (line, status) per image: a TUM line plus inlier count ("ok"), `# name: not
    localized` ("failed"), or `# name: error: ...` for an unreadable image ("error")."""
    scene_map = SceneMap.load(map_dir)
    localizer = make_localizer(scene_map, method)
    for path in images:
        try:
            image = read_image(path)
        except InputError as err:
            yield f"error: {err}", "error"
            continue
        h, w = image.shape[:2]
        camera = (Camera(w, h, *intrinsics) if intrinsics
                  else scene_map.camera.scaled_to(w, h))
        loc = localizer.localize(image, camera)
        est = loc.estimate
        if est.success:
            yield f"{tum_line(Path(path).name, est.world_from_cam)} {est.num_inliers}", "ok"
        else:
            yield f"# {Path(path).name}: not localized ({est.num_inliers} inliers)", "failed"
