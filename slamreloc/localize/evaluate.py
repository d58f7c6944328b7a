"""Localize every frame of a split and score it against ground truth (the REPORT.json contract).

`evaluate_map` takes a loaded map and dataset and returns the report; the references other than
the dataset's poses are prepared (matched and aligned on the map's training cameras) by
`prepare_reference`. Reading and checking files, and writing the report, are the command's
(`slamreloc.cli.jobs`)."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from rich.table import Table

from slamreloc.datasets import Dataset, read_frame_image, read_reference
from slamreloc.datasets.poses import FrameKey, match_poses
from slamreloc.errors import InputError
from slamreloc.geometry import (Rigid3, Sim3, align_poses, distinct_stamps, pose_error,
                                write_tum_trajectory)
from slamreloc.localize.localizer import Localizer, make_localizer
from slamreloc.map.scene_map import SceneMap
from slamreloc.runtime.progress import console, shown, track
from slamreloc.types import Frame

THRESHOLDS = {"1cm1deg": (0.01, 1.0), "2cm2deg": (0.02, 2.0), "5cm5deg": (0.05, 5.0),
              "10cm5deg": (0.10, 5.0)}


@dataclass
class QueryResult:
    name: str
    world_from_cam: Rigid3 | None  # None: not localized
    num_inliers: int
    translation_error_m: float  # inf when not localized
    rotation_error_deg: float
    timings_ms: dict
    timestamp: float = 0.0  # the frame's timestamp (seconds), the TUM file's first column


def evaluate_frames(localizer: Localizer, frames: list[Frame], progress: bool = True,
                    refine: Callable[[Frame, Rigid3], Rigid3] | None = None
                    ) -> list[QueryResult]:
    """refine: optional `(frame, world_from_cam) -> world_from_cam` applied to each localized
    pose (depth ICP against the map's surface), timed as `icp`."""
    if not frames:
        raise InputError("no query frames to evaluate")
    unposed = next((f for f in frames if f.world_from_cam is None), None)
    if unposed is not None:  # before the work, not after it
        raise InputError(f"{unposed.image_path}: query frame has no ground-truth pose")
    localizer.extractor.check_frames(frames)
    results = []
    for frame in track(frames, f"localizing ({localizer.method})", enabled=progress):
        image = read_frame_image(frame)
        if image.shape[:2] != (frame.camera.height, frame.camera.width):
            raise InputError(f"{frame.image_path}: image is {image.shape[1]}x{image.shape[0]}, "
                             f"its camera is {frame.camera.width}x{frame.camera.height}")
        loc = localizer.localize(image, frame.camera)
        est = loc.estimate.world_from_cam
        if refine is not None and est is not None:
            t0 = time.perf_counter()
            est = refine(frame, est)
            loc.timings_ms["icp"] = 1000 * (time.perf_counter() - t0)
            loc.timings_ms["total"] += loc.timings_ms["icp"]
        dt, dr = pose_error(est, frame.world_from_cam) if est else (np.inf, np.inf)
        results.append(QueryResult(frame.name, est, loc.estimate.num_inliers, dt, dr,
                                   loc.timings_ms, frame.timestamp))
    return results


@dataclass(frozen=True)
class EvaluationConfig:
    """How the queries are localized: `method` regressor | matching on `device`; `guided`
    False leaves the regressor's guided refinement out (`RegressorLocalizer`; the matching
    baseline has none); `progress`: show a progress bar."""

    method: str = "regressor"
    device: str = "cpu"
    guided: bool = True
    progress: bool = True

    def localizer(self, scene_map: SceneMap) -> Localizer:
        kwargs = {"guided": None} if not self.guided and self.method == "regressor" else {}
        return make_localizer(scene_map, self.method, device=self.device, **kwargs)


@dataclass
class Evaluation:
    """`evaluate_map`'s result: the report (the REPORT.json contract), the per-query results
    (map frame) and the frames they belong to, in order."""

    report: dict
    results: list[QueryResult]
    frames: list[Frame]


def query_frames(dataset: Dataset, split: str) -> list[Frame]:
    """The frames of `split`; InputError naming the dataset where it has none."""
    frames = dataset.frames(split)
    if not frames:
        raise InputError(f"{dataset.root}: split '{split}' has no frames to evaluate")
    return frames


def evaluate_map(scene_map: SceneMap, dataset: Dataset, split: str = "test",
                 config: EvaluationConfig = EvaluationConfig(),
                 refine: Callable[[Frame, Rigid3], Rigid3] | None = None,
                 references: list[ScoringReference] | tuple[ScoringReference, ...] = (),
                 localizer: Localizer | None = None) -> Evaluation:
    """Localize `split` of `dataset` against `scene_map` (a `localizer` made from `config`
    unless one is given) and score it against the dataset's poses (or the ones
    `load_dataset(..., poses)` put in their place) and against each prepared reference.
    refine: `evaluate_frames`'s; the report's `refine` says "depth" when one is given."""
    frames = query_frames(dataset, split)
    localizer = localizer or config.localizer(scene_map)
    own = session_alignment(scene_map, dataset, frames)
    results = evaluate_frames(localizer, frames, config.progress, refine)
    if own is not None:  # scored in the dataset's frame; the estimates stay in the map's
        scored = rescore(results, {f.name: f.world_from_cam for f in frames}, own[0])
        results = [replace(r, translation_error_m=s.translation_error_m,
                           rotation_error_deg=s.rotation_error_deg)
                   for r, s in zip(results, scored)]
    summary = summarize(results, config.method)
    summary["refine"] = "depth" if refine is not None else None
    # the regressor's last refinement on the map's database points (localize.guided)
    summary["guided_refinement"] = localizer.guided is not None
    summary["map"] = {"parameters": scene_map.regressor.num_parameters(),
                      "size_bytes": scene_map.size_bytes(),
                      "database_bytes": scene_map.database_bytes(),
                      "n_database_descriptors": scene_map.info.n_labelled}
    summary["device"] = localizer.device.type
    # the numbers above are scored against `reference`: the dataset's poses or a pose file
    summary["reference"] = dataset.poses_source
    summary["dataset"] = {"root": str(Path(dataset.root).resolve()), "split": split,
                          "poses": dataset.poses_source}
    summary["references"] = {r.label: r.score(results) for r in references}
    summary["alignment"] = None if own is None else own[1]
    summary["per_query"] = [
        {"name": r.name, "translation_error_m": r.translation_error_m if r.world_from_cam else None,
         "rotation_error_deg": r.rotation_error_deg if r.world_from_cam else None,
         "num_inliers": r.num_inliers} for r in results]
    return Evaluation(summary, results, frames)


def session_alignment(scene_map: SceneMap, dataset: Dataset, queries: list[Frame]
                      ) -> tuple[Sim3, dict] | None:
    """A map a SLAM session learned (`slam --out`, recorded poses "slam") is in that session's
    frame, not the dataset's: (dataset_from_map, its record), the similarity fitted on the
    map's keyframes that the dataset has poses of (never the queries), by which estimates are
    scored against the dataset's poses; None for a map in its dataset's frame."""
    frames = scene_map.session_frames()
    if frames is None:
        return None
    query_names = {f.name for f in queries}
    truth = {f.name: f.world_from_cam for f in dataset.frames("all")
             if f.world_from_cam is not None and f.name not in query_names}
    map_from_cam = {n: pose for n, pose in frames.items() if n in truth}
    queried = sum(n in query_names for n in frames)
    if len(map_from_cam) < 3 and queried:
        raise InputError(
            f"{scene_map.root}: a map a SLAM session learned is scored after fitting the "
            f"dataset's poses onto its keyframes that are not queried, and {queried} of its "
            f"{len(frames)} keyframes are among the queries (only {len(map_from_cam)} left): "
            "evaluate it on frames the session did not track (another split)")
    ref_from_map, record = align_to_reference(map_from_cam, truth,
                                              f"{dataset.root}: the map's keyframes")
    return ref_from_map, {**record, "aligned": True, "on": "the map's keyframes"}


@dataclass
class ScoringReference:
    """A reference pose file, prepared before any query is localized: its poses of the queries
    (world_from_cam in its own frame, by query name) and how estimates move from the map's
    frame into that frame (fitted on the map's training cameras only)."""

    label: str  # the report's key and the table's row
    source: Path  # resolved
    query_world_from_cam: dict[str, Rigid3]
    ref_from_map: Sim3 | None  # None: the reference is in the map's frame already
    alignment: dict  # `reference_alignment`'s record

    def score(self, results: list[QueryResult]) -> dict:
        """The report's `references[label]` entry."""
        return {"file": str(self.source), "alignment": self.alignment,
                **score_against(results, self.query_world_from_cam, self.ref_from_map)}


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


def within(translation_m, rotation_deg) -> dict[str, np.ndarray]:
    """Per query, whether it is within each of THRESHOLDS (metres, degrees; a failure is inf,
    so outside all)."""
    t = np.asarray(translation_m, dtype=float)
    r = np.asarray(rotation_deg, dtype=float)
    return {k: (t <= tt) & (r <= rr) for k, (tt, rr) in THRESHOLDS.items()}


def recalls(translation_m, rotation_deg) -> dict[str, float]:
    """Fraction of queries within each of THRESHOLDS (see `within`); 0 for no queries."""
    return {k: float(np.mean(ok)) if len(ok) else 0.0
            for k, ok in within(translation_m, rotation_deg).items()}


def summarize(results: list[QueryResult], method: str) -> dict:
    """Median errors, recalls, median stage timings (failures count as infinite error)."""
    t = np.array([r.translation_error_m for r in results])
    r = np.array([r.rotation_error_deg for r in results])
    finite = lambda v: float(v) if np.isfinite(v) else None  # noqa: E731 - JSON has no inf
    stages = [k for k in ("features", "regressor", "pnp", "icp", "total")
              if any(k in q.timings_ms for q in results)]
    timing = {k: float(np.median([q.timings_ms[k] for q in results if k in q.timings_ms]))
              for k in stages}
    return {
        "method": method, "n_queries": len(results),
        "n_localized": int(np.sum([q.world_from_cam is not None for q in results])),
        "median_translation_m": finite(np.median(t)) if len(t) else None,
        "median_rotation_deg": finite(np.median(r)) if len(r) else None,
        "recall": recalls(t, r),
        "timing_ms": timing,
    }


def align_to_reference(map_from_cam: dict[str, Rigid3], reference: dict[str, Rigid3],
                       source: str | None = None) -> tuple[Sim3, dict]:
    """ref_from_map: the similarity that takes the map's world frame to a reference's, fitted
    on the poses of the frames both hold (`geometry.align_poses`: rotation from the cameras'
    orientations, scale and translation from their centres): the map's *training* cameras,
    never queries. Returns it and its record: scale, frames used, median residuals (metres
    of the reference, degrees), the 3x4 matrix [s R | t]. `source` names the reference in
    the error raised when fewer than 3 frames are shared."""
    names = sorted(set(map_from_cam) & set(reference))
    if len(names) < 3:
        where = f"{source}: " if source else ""
        raise InputError(f"{where}only {len(names)} training frames have a reference pose; a "
                         "similarity fit needs at least 3")
    where = f"{source}: " if source else ""
    for label, poses in (("the reference's", reference), ("the map's", map_from_cam)):
        centres = np.array([poses[n].translation for n in names])
        if np.sqrt(np.mean(np.sum((centres - centres.mean(0)) ** 2, axis=1))) < 1e-6:
            raise InputError(f"{where}{label} {len(names)} shared training cameras all lie at "
                             "one point: no similarity can be fitted to them")
    ref_from_map = align_poses([map_from_cam[n] for n in names], [reference[n] for n in names])
    if not ref_from_map.scale > 0:  # centres in mirrored or unrelated order
        raise InputError(f"{where}the fitted similarity has scale {ref_from_map.scale:.4g} "
                         f"over {len(names)} shared training cameras: the reference's positions "
                         "do not follow the map's (mirrored, or not these cameras' poses)")
    return ref_from_map, {
        "scale": ref_from_map.scale, "n_frames": len(names),
        **residual_medians(map_from_cam, reference, names, ref_from_map),
        "matrix": np.column_stack([ref_from_map.scale * ref_from_map.rotation,
                                   ref_from_map.translation]).tolist()}


def residual_medians(map_from_cam: dict[str, Rigid3], reference: dict[str, Rigid3],
                     names: list[str], ref_from_map: Sim3 | None = None) -> dict:
    """Median pose differences over `names` between the map's cameras, moved by
    `ref_from_map` (None: as they are), and the reference's: metres of the reference,
    degrees."""
    moved = ((lambda p: p) if ref_from_map is None else ref_from_map.apply_to_pose)
    errors = np.array([pose_error(moved(map_from_cam[n]), reference[n]) for n in names])
    return {"median_residual_m": float(np.median(errors[:, 0])),
            "median_residual_deg": float(np.median(errors[:, 1]))}


IDENTITY_RESIDUAL = (0.001, 0.05)  # metres, degrees: a reference whose training cameras lie
# this close (medians) to the map's without a transform is in the map's frame already


def reference_alignment(map_from_cam: dict[str, Rigid3], reference: dict[str, Rigid3],
                        source: str | None = None) -> tuple[Sim3 | None, dict]:
    """How to move estimates (map frame) into a reference's frame, from the training cameras
    both hold (`map_from_cam`: the map's training world_from_cam by frame name, queries left
    out; `reference`: the reference's world_from_cam by the same names). None (no transform)
    where the reference agrees with the map's frame already: the median residuals of the
    identity are below IDENTITY_RESIDUAL; else `align_to_reference`'s similarity. The record
    is `align_to_reference`'s plus `aligned` (whether a transform is applied); without one,
    scale 1, the identity matrix and the identity's residuals."""
    names = sorted(set(map_from_cam) & set(reference))
    if len(names) >= 3:
        residual = residual_medians(map_from_cam, reference, names)
        if (residual["median_residual_m"] < IDENTITY_RESIDUAL[0]
                and residual["median_residual_deg"] < IDENTITY_RESIDUAL[1]):
            return None, {"scale": 1.0, "n_frames": len(names), **residual,
                          "matrix": np.eye(4)[:3].tolist(), "aligned": False}
    ref_from_map, record = align_to_reference(map_from_cam, reference, source)
    return ref_from_map, {**record, "aligned": True}


REFERENCE_KEYS = ("n_queries", "n_localized", "median_translation_m", "median_rotation_deg",
                  "recall")


def score_against(results: list[QueryResult], reference: dict[str, Rigid3],
                  ref_from_map: Sim3 | None = None) -> dict:
    """`summarize`'s scores (REFERENCE_KEYS) of the estimates against a reference's poses of
    the queries (by name), in the reference's frame (`rescore`); the queries it lacks are
    left out and counted in `n_queries_without_reference`."""
    scored = rescore(results, reference, ref_from_map)
    summary = summarize(scored, "")
    return {**{k: summary[k] for k in REFERENCE_KEYS},
            "n_queries_without_reference": len(results) - len(scored)}


def rescore(results: list[QueryResult], reference: dict[str, Rigid3],
            ref_from_map: Sim3 | None = None) -> list[QueryResult]:
    """The same estimates scored against other reference poses (by frame name), after moving
    them into the reference's frame with `ref_from_map`; frames the reference lacks are left
    out."""
    out = []
    for q in results:
        if q.name not in reference:
            continue
        est = q.world_from_cam
        if est is not None and ref_from_map is not None:
            est = ref_from_map.apply_to_pose(est)
        dt, dr = pose_error(est, reference[q.name]) if est else (np.inf, np.inf)
        out.append(replace(q, world_from_cam=est, translation_error_m=dt,
                           rotation_error_deg=dr))
    return out


def write_tum(path: Path, results: list[QueryResult]) -> None:
    """Localized frames as TUM lines `timestamp tx ty tz qx qy qz qw` (camera-to-world, as
    evo reads them); failures are left out. The first column is the frame's timestamp, or
    its index in `results` when timestamps repeat (several sequences); the frame names go to
    the sidecar `<path stem>.names.txt` (`stamp name` per line)."""
    stamps = distinct_stamps([q.timestamp for q in results])
    done = [(t, q) for t, q in zip(stamps, results) if q.world_from_cam is not None]
    write_tum_trajectory(path, [t for t, _ in done], [q.world_from_cam for _, q in done],
                         names=[q.name for _, q in done])


def print_summary(summaries: list[dict]) -> None:
    """A rich table of evaluation summaries: one row per method scored against its primary
    reference (the dataset's poses or --poses), then one per --reference; notes on how each
    reference was aligned and which queries it lacks follow the table."""
    table = Table(title="relocalization")
    for col in ("method", "reference", "localized", "median", *THRESHOLDS, "ms/query"):
        table.add_column(col)
    notes = []
    for s in summaries:
        primary = s.get("reference", "dataset")
        rows = [(s["method"], "dataset" if primary == "dataset" else shown(Path(primary).name), s,
                 f"{s['timing_ms'].get('total', float('nan')):.0f}")]
        for label, ref in s.get("references", {}).items():
            rows.append(("", shown(label), ref, "-"))
            notes.append(_reference_note(label, ref))
        for method, reference, r, ms in rows:
            med_t, med_r = r["median_translation_m"], r["median_rotation_deg"]
            median = "inf" if med_t is None else f"{100 * med_t:.1f} cm, {med_r:.2f} deg"
            table.add_row(method, reference, f"{r['n_localized']}/{r['n_queries']}", median,
                          *(f"{100 * r['recall'][k]:.1f} %" for k in THRESHOLDS), ms)
    console.print(table)
    for note in notes:
        console.print(note)


def _reference_note(label: str, ref: dict) -> str:
    a = ref["alignment"]
    how = (f"aligned by a similarity (scale {a['scale']:.4f})" if a["aligned"]
           else "in the map's frame already (no transform)")
    note = (f"reference {shown(label)}: {how}, {a['n_frames']} training cameras, residual median "
            f"{100 * a['median_residual_m']:.2f} cm / {a['median_residual_deg']:.2f} deg")
    missing = ref.get("n_queries_without_reference", 0)
    if missing:
        note += f"; {missing} queries it has no pose for are left out"
    return note
