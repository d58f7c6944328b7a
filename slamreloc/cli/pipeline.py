"""Entry functions behind the CLI: evaluate a map on a dataset, localize loose images."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from slamreloc.datasets import Dataset, load_dataset, read_image, read_reference
from slamreloc.datasets.poses import FrameKey, match_poses
from slamreloc.errors import InputError
from slamreloc.localize.evaluate import (
    QueryResult,
    evaluate_frames,
    reference_alignment,
    score_against,
    summarize,
    write_tum,
)
from slamreloc.io.fileio import check_outputs, write_json
from slamreloc.geometry import Rigid3, Sim3, tum_line
from slamreloc.localize.localizer import Localizer, make_localizer
from slamreloc.map.format import check_is_map
from slamreloc.map.scene_map import SceneMap
from slamreloc.map.surface import frame_cloud, refine_pose
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


@dataclass
class ScoringReference:
    """An `evaluate --reference` file, prepared before any query is localized: its poses of
    the queries (world_from_cam in its own frame, by query name) and how estimates move from
    the map's frame into that frame (fitted on the map's training cameras only)."""

    label: str  # `reference_labels`: the report's key and the table's row
    source: Path  # resolved
    query_world_from_cam: dict[str, Rigid3]
    ref_from_map: Sim3 | None  # None: the reference is in the map's frame already
    alignment: dict  # `evaluate.reference_alignment`'s record

    def score(self, results: list[QueryResult]) -> dict:
        """The report's `references[label]` entry."""
        return {"file": str(self.source), "alignment": self.alignment,
                **score_against(results, self.query_world_from_cam, self.ref_from_map)}


def reference_labels(paths: list[Path]) -> list[str]:
    """Short distinct labels of the --reference paths: the file name, with as many parent
    folders as tell two apart (and a COLMAP model's `sparse/0` its project folder's name).
    InputError for a path given twice."""
    parts = [Path(p).resolve().parts for p in paths]
    depth = [1] * len(paths)
    for i, p in enumerate(parts):  # `.../redkitchen/sparse/0` -> `redkitchen/sparse/0`
        while depth[i] < len(p) and (p[-depth[i]].isdigit() or p[-depth[i]] == "sparse"):
            depth[i] += 1
    while True:
        labels = ["/".join(p[-d:]) for p, d in zip(parts, depth)]
        clash = [i for i, label in enumerate(labels) if labels.count(label) > 1]
        if not clash:
            return labels
        if all(depth[i] >= len(parts[i]) for i in clash):
            raise InputError(f"{paths[clash[0]]}: --reference given twice")
        for i in clash:
            depth[i] = min(depth[i] + 1, len(parts[i]))


def prepare_reference(path: Path, label: str, scene_map: SceneMap, dataset: Dataset,
                      queries: list[Frame]) -> ScoringReference:
    """Read a reference (`datasets.read_reference`), match it to the map's training frames
    and the queries (`match_poses`: training frames the dataset holds by name, image path or
    timestamp, the others by name), and align it on the training frames that are not queries
    of this evaluation. InputError naming the file where it matches no frame, no query, or
    fewer than 3 training frames."""
    reference = read_reference(path)
    root = Path(dataset.root)
    frames = {f.name: f for f in dataset.frames("all")}
    query_names = {f.name for f in queries}
    db = scene_map.database
    training = [(n, m) for n, m in zip(db.frame_names, db.world_from_cam.reshape(-1, 4, 4))
                if n not in query_names]
    keys = [FrameKey.of(frames[n], root) if n in frames else FrameKey(n) for n, _ in training]
    keys += [FrameKey.of(f, root) for f in queries]
    matched = match_poses(reference, keys)
    if all(p is None for p in matched):
        raise InputError(f"{reference.source}: names none of the map's training frames nor "
                         f"the queries ({reference.count()}, the first {reference.first()}; "
                         f"the frames are named like {keys[0].name!r})")
    ref_training = {n: p for (n, _), p in zip(training, matched) if p is not None}
    ref_queries = {f.name: p for f, p in zip(queries, matched[len(training):]) if p is not None}
    if not ref_queries:
        raise InputError(f"{reference.source}: has a pose for none of the {len(queries)} "
                         f"queries (it has {len(ref_training)} of the map's training frames): "
                         "nothing to score")
    map_from_cam = {n: Rigid3.from_matrix(m, tol=1e-2, source=f"{scene_map.root}: frame {n}")
                    for n, m in training}
    ref_from_map, alignment = reference_alignment(map_from_cam, ref_training,
                                                  str(reference.source))
    return ScoringReference(label, reference.source, ref_queries, ref_from_map, alignment)


def _localizer(scene_map: SceneMap, method: str, guided: bool, **kwargs) -> Localizer:
    """`make_localizer`; `guided` False: the regressor without its guided refinement (the
    matching baseline has none)."""
    if not guided and method == "regressor":
        kwargs["guided"] = None
    return make_localizer(scene_map, method, **kwargs)


def evaluate_method(scene_map: SceneMap, dataset_dir: Path, split: str = "test",
                    method: str = "regressor", device: str = "cpu", progress: bool = True,
                    depth: bool = False, poses: Path | None = None,
                    references: list[Path] | tuple[Path, ...] = (), guided: bool = True):
    """Localize a split with one method (`depth`: refine each pose by ICP of the frame's depth
    against the map's surface) and score it against the dataset's poses, or `poses` (a pose
    file, `datasets.poses`), and against each of `references` (aligned to the map's frame on
    its training cameras). `guided`: False leaves the regressor's guided refinement out
    (`RegressorLocalizer`). Everything is read and checked before the work. Returns (report
    dict, per-query results, frames)."""
    labels = reference_labels(list(references))
    dataset = load_dataset(dataset_dir, poses)
    frames = dataset.frames(split)
    if not frames:
        raise InputError(f"{dataset_dir}: split '{split}' has no frames to evaluate")
    unposed = next((f for f in frames if f.world_from_cam is None), None)
    if unposed is not None and dataset.poses_source != "dataset":
        raise InputError(f"{dataset.poses_source}: no pose for query frame {unposed.name} "
                         "(--poses gives the queries' ground truth)")
    scoring = [prepare_reference(Path(p), label, scene_map, dataset, frames)
               for p, label in zip(references, labels)]
    refine = depth_refiner(scene_map, dataset) if depth else None
    localizer = _localizer(scene_map, method, guided, device=device)
    results = evaluate_frames(localizer, frames, progress, refine)
    summary = summarize(results, method)
    summary["refine"] = "depth" if depth else None
    # the regressor's last refinement on the map's database points (guided_matching)
    summary["guided_refinement"] = localizer.guided is not None
    summary["map"] = {"parameters": scene_map.regressor.num_parameters(),
                      "size_bytes": scene_map.size_bytes(),
                      "database_bytes": scene_map.database_bytes(),
                      "n_database_descriptors": scene_map.info.n_labelled}
    summary["device"] = localizer.device.type
    # the numbers above are scored against `reference`: the dataset's poses or --poses
    summary["reference"] = dataset.poses_source
    summary["dataset"] = {"root": str(Path(dataset_dir).resolve()), "split": split,
                          "poses": dataset.poses_source}
    summary["references"] = {r.label: r.score(results) for r in scoring}
    summary["per_query"] = [
        {"name": r.name, "translation_error_m": r.translation_error_m if r.world_from_cam else None,
         "rotation_error_deg": r.rotation_error_deg if r.world_from_cam else None,
         "num_inliers": r.num_inliers} for r in results]
    return summary, results, frames


def run_evaluation(map_dir: Path, dataset_dir: Path, report: Path, split: str = "test",
                   method: str = "regressor", trajectory: Path | None = None,
                   plot: Path | None = None, device: str = "cpu", progress: bool = True,
                   depth: bool = False, poses: Path | None = None,
                   references: list[Path] | tuple[Path, ...] = (), guided: bool = True) -> dict:
    """Localize a split, write REPORT.json (and the estimated poses as a TUM `trajectory`, a
    plot); returns the report. `poses`, `references`, `guided`: `evaluate_method`."""
    check_is_map(map_dir)  # what the inputs are, then where the outputs may go
    check_outputs({"--report": report, "--trajectory": trajectory, "--plot": plot},
                  {"the map": map_dir, "the dataset": dataset_dir, "--poses": poses,
                   **{f"--reference {p}": p for p in references}})
    summary, results, frames = evaluate_method(SceneMap.load(map_dir), dataset_dir, split,
                                               method, device, progress, depth, poses,
                                               references, guided)
    write_json(report, summary)
    if trajectory:
        write_tum(trajectory, results)
    if plot:
        from slamreloc.localize.plots import plot_evaluation

        plot_evaluation(plot, {method: results}, frames)
    return summary


def localize_images(map_dir: Path, images: list[Path],
                    intrinsics: Camera | tuple[float, float, float, float] | None = None,
                    method: str = "regressor", guided: bool = True):
    """Yield (line, status) per image (or per frame of a ROS bag among `images`): a TUM line
    plus inlier count ("ok"), `# name: not localized` ("failed"), or `error: ...` for an
    image that cannot be read or is out of bounds ("error"). `intrinsics`: a Camera (any lens
    model, scaled to each image), pinhole (fx, fy, cx, cy) in pixels, else the bag's camera
    or the map's, scaled to each image. `guided`: `evaluate_method`."""
    if intrinsics is not None and not isinstance(intrinsics, Camera):
        problem = camera_problem(1, 1, *intrinsics)
        if problem:
            raise InputError(f"--intrinsics: {problem}")
    scene_map = SceneMap.load(map_dir)
    localizer = _localizer(scene_map, method, guided)
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
