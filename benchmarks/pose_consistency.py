"""Do a dataset's poses agree with a map's, as the images see it? (classical matching + PnP)

Two curves over frame order, each frame registered by the pseudo-label stage's matcher (mutual
nearest neighbours with a ratio test against the map's labelled descriptors) and PnP-RANSAC,
no learned regressor involved:
- the map's own frames, each against the labels of frames more than --leave-out frames away
  (how well the map's poses agree with each other), and
- DATASET's frames against the whole map, compared with DATASET's own poses (how well those
  agree with the map's).

    python benchmarks/pose_consistency.py MAP DATASET [--split all] [--stride 5] \
        [--leave-out 30] [--plot consistency.png]

On RedKitchen (issue 9's split) this shows the seq-01 ground truth bending between its two
halves: docs/history.md, "What bounds the update on RedKitchen".
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from slamreloc.datasets import load_dataset
from slamreloc.features.extract import extract_frames
from slamreloc.features import make_extractor
from slamreloc.geometry import Rigid3, pose_error
from slamreloc.localize.pnp import PnPConfig, estimate_pose
from slamreloc.pseudo_label.register import Database, RegistrationConfig
from slamreloc.map.scene_map import SceneMap
from slamreloc.types import Camera

REG = RegistrationConfig()
PNP = PnPConfig(max_error_px=REG.pnp_max_error_px, min_inliers=REG.min_inliers)


def register(db: Database, keypoints: np.ndarray, descriptors: np.ndarray,
             camera: Camera) -> Rigid3 | None:
    """world_from_cam by matching to `db` and PnP-RANSAC; None when it fails."""
    m = db.match(descriptors.astype(np.float32), REG.ratio, REG.same_point_m)
    if len(m) < PNP.min_inliers:
        return None
    est = estimate_pose(keypoints[m[:, 0]], db.points[m[:, 1]].astype(np.float64), camera, PNP)
    return est.world_from_cam if est.success else None


def map_self_consistency(scene_map: SceneMap, stride: int, leave_out: int) -> list[tuple]:
    """(frame order, translation m, rotation deg) per stride-th map frame against the labels
    of the map's frames more than `leave_out` frames away."""
    db = scene_map.database
    poses = db.world_from_cam.reshape(-1, 4, 4)
    out = []
    for k in range(0, len(db.frame_names), stride):
        q, far = db.frame_index == k, np.abs(db.frame_index - k) > leave_out
        est = register(Database(db.descriptors[far], db.points[far]), db.keypoints[q],
                       db.descriptors[q], scene_map.camera)
        if est is not None:
            out.append((k, *pose_error(est, Rigid3.from_matrix(poses[k]))))
    return out


def dataset_consistency(scene_map: SceneMap, dataset_dir: Path, split: str,
                        stride: int) -> list[tuple]:
    """(frame order, translation m, rotation deg) per stride-th posed frame of the split."""
    frames = [f for f in load_dataset(dataset_dir).frames(split)[::stride]
              if f.world_from_cam is not None]
    cfg = dict(scene_map.meta["features"])
    feats = extract_frames(frames, make_extractor(cfg.pop("name"), **cfg), progress=True)
    db = Database(scene_map.database.descriptors, scene_map.database.points)
    out = []
    for k, (f, ft) in enumerate(zip(frames, feats)):
        est = register(db, ft.keypoints, ft.descriptors, f.camera)
        if est is not None:
            out.append((k * stride, *pose_error(est, f.world_from_cam)))
    return out


def blocks(rows: list[tuple], size: int) -> list[str]:
    lines = []
    for lo in range(0, int(max(r[0] for r in rows)) + 1, size):
        b = np.array([r[1:] for r in rows if lo <= r[0] < lo + size])
        if len(b):
            lines.append(f"| {lo}-{lo + size - 1} | {len(b)} | {100 * np.median(b[:, 0]):.1f} cm"
                         f" | {np.median(b[:, 1]):.2f} deg |")
    return lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("map", type=Path)
    ap.add_argument("dataset", type=Path)
    ap.add_argument("--split", default="all")
    ap.add_argument("--stride", type=int, default=5)
    ap.add_argument("--leave-out", type=int, default=30)
    ap.add_argument("--block", type=int, default=20, help="frames per row of the tables")
    ap.add_argument("--plot", type=Path, default=None)
    args = ap.parse_args()
    scene_map = SceneMap.load(args.map)
    own = map_self_consistency(scene_map, args.stride, args.leave_out)
    new = dataset_consistency(scene_map, args.dataset, args.split, args.stride)
    header = ["| frames | registered | median translation | median rotation |", "|---|---|---|---|"]
    for title, rows in ((f"map frames vs the map's labels > {args.leave_out} frames away", own),
                        (f"{args.dataset} ({args.split}) vs the map", new)):
        print(f"\n{title}: median {100 * np.median([r[1] for r in rows]):.1f} cm / "
              f"{np.median([r[2] for r in rows]):.2f} deg over {len(rows)} frames\n")
        print("\n".join(header + blocks(rows, args.block)))
    if args.plot:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, axes = plt.subplots(1, 2, figsize=(12, 4))
        for rows, label in ((own, "map frames (leave-out)"), (new, "dataset frames")):
            r = np.array(rows)
            axes[0].plot(r[:, 0], 100 * r[:, 1], ".-", label=label)
            axes[1].plot(r[:, 0], r[:, 2], ".-", label=label)
        axes[0].set(xlabel="frame (order in its sequence)", ylabel="translation error (cm)")
        axes[1].set(xlabel="frame (order in its sequence)", ylabel="rotation error (deg)")
        for ax in axes:
            ax.grid(alpha=0.3)
            ax.legend()
        fig.tight_layout()
        fig.savefig(args.plot, dpi=110)
        print(f"\nplot: {args.plot}")


if __name__ == "__main__":
    main()
