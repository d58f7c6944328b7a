"""How well can any image-consistent estimate score against the dataset's depth-SLAM poses?

The live-mapping targets on RedKitchen are scored against two references that disagree by a few
cm / deg: the dataset's poses (depth SLAM, the depth camera's) and sfm_pgt (SfM, the RGB
camera's, from the images alone). A map built from the images (feature links, RGB
relocalization) follows the images' geometry, so its scores against the dataset's poses are
bounded by how far the images' own true poses are from them. This script takes the SfM poses
as a perfect image-consistent estimate, made metric (the similarity fitted on seq-01 sets its
scale), and scores them against the dataset's poses under each protocol of
`benchmarks/live_map_benchmark.py`:

- learned: `evaluate`'s protocol for the saved map of seq-01: a similarity fitted on seq-01's
  cameras (`geometry.align_poses`, as `evaluate` fits it on the map's keyframes), recall of
  seq-02 within 5 cm / 5 deg (and 2 cm / 2 deg, 1 cm / 1 deg);
- multi: the multi-session ATE: the reference moved onto the estimate's seq-01 cameras by one
  rigid fit, the RMSE over seq-02;
- stream: the one-stream ATE: SE(3)-aligned on all 600 cameras, RMSE over all of them.

    python -m benchmarks.reference_ceiling ../shared/data/7scenes_redkitchen
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from slamreloc.datasets import load_dataset
from slamreloc.geometry import align_poses, pose_error
from slamreloc.slam.metrics import ate_rmse

SFM = "sfm_pgt/poses.txt"


def ceiling(data: Path) -> dict:
    """The SfM poses' scores against the dataset's poses under the three protocols."""
    ds, sfm = load_dataset(data), load_dataset(data, data / SFM)
    truth = {f.name: f.world_from_cam for f in ds.frames("all")}
    image = {f.name: f.world_from_cam for f in sfm.frames("all")}
    first = [f.name for f in ds.frames("seq-01")]
    second = [f.name for f in ds.frames("seq-02")]
    # metric, in seq-01's frame of the dataset's poses: the similarity evaluate would fit
    fit = align_poses([image[n] for n in first], [truth[n] for n in first])
    metric = {n: fit.apply_to_pose(p) for n, p in image.items()}
    errors = np.array([pose_error(metric[n], truth[n]) for n in second])
    recall = {f"{k}cm{k}deg": float(np.mean((errors[:, 0] < k / 100) & (errors[:, 1] < k)))
              for k in (5, 2, 1)}
    map_from_ref = align_poses([truth[n] for n in first], [metric[n] for n in first],
                               with_scale=False).rigid
    multi = ate_rmse([metric[n] for n in second], [map_from_ref @ truth[n] for n in second])
    names = first + second
    stream = ate_rmse([metric[n] for n in names], [truth[n] for n in names], align=True)
    return {"scale": fit.scale, "learned_recall": recall,
            "learned_median": [float(np.median(errors[:, 0])), float(np.median(errors[:, 1]))],
            "multi_ate_m": multi, "stream_ate_m": stream}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("data", type=Path, help="the 7-Scenes RedKitchen folder with sfm_pgt/")
    r = ceiling(ap.parse_args().data)
    rec, med = r["learned_recall"], r["learned_median"]
    print(f"SfM poses (scale {r['scale']:.4f} to metres) against the dataset's poses:")
    print("| protocol | the images' own poses score |")
    print("|---|---|")
    print(f"| learned map, seq-02 after a fit on seq-01 | 5cm5deg {100 * rec['5cm5deg']:.1f} %, "
          f"2cm2deg {100 * rec['2cm2deg']:.1f} %, 1cm1deg {100 * rec['1cm1deg']:.1f} %, "
          f"median {100 * med[0]:.2f} cm / {med[1]:.2f} deg |")
    print(f"| multi-session ATE of seq-02 in seq-01's frame | {100 * r['multi_ate_m']:.2f} cm |")
    print(f"| one-stream ATE, SE(3) on all 600 | {100 * r['stream_ate_m']:.2f} cm |")


if __name__ == "__main__":
    main()
