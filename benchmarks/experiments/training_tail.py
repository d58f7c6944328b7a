"""A training tail without augmentation: does fitting the labels tighter make poses finer?

    python -m benchmarks.experiments.training_tail MAP [MAP ...] DATASET [--poses FILE] --out tail.md

The regressor trains with input noise and input dropout (`TrainConfig.noise`,
`input_dropout`): robustness to the descriptor changes of new views, at the price of a looser
fit to the labels (the table's final training loss: the mean distance in the last epoch, under
that epoch's augmentation). Each variant continues a trained map's regressor
for a few epochs (`train_regressor(..., fine_tune=True)`) with other augmentation and learning
rate, in memory, and scores the regressor on the dataset's test frames against the poses the
map was trained on; `as trained` is the map itself. Nothing is written to the maps.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from benchmarks.label_levers import query_features, score_method
from slamreloc.datasets import load_dataset
from slamreloc.localize.evaluate import THRESHOLDS
from slamreloc.regressor.train import TrainConfig, train_regressor
from slamreloc.map.scene_map import SceneMap

NO_AUGMENTATION = {"noise": 0.0, "input_dropout": 0.0}
TAILS = {  # name: TrainConfig fields of the extra epochs (None: the map as trained)
    "as trained": None,
    "10 epochs, no augmentation, lr 2e-4": {"epochs": 10, "lr": 2e-4, "lr_halvings": 2,
                                            **NO_AUGMENTATION},
    "10 epochs, no augmentation, lr 1e-3": {"epochs": 10, "lr": 1e-3, "lr_halvings": 3,
                                            **NO_AUGMENTATION},
}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("maps", type=Path, nargs="+")
    ap.add_argument("dataset", type=Path)
    ap.add_argument("--poses", type=Path, default=None)
    ap.add_argument("--tails", nargs="+", default=list(TAILS), choices=list(TAILS))
    ap.add_argument("--out", type=Path, default=Path("tail.md"))
    args = ap.parse_args()
    frames = load_dataset(args.dataset, args.poses).frames("test")
    feats = None
    head = " / ".join(THRESHOLDS)
    lines = [(f"`{args.dataset}`, scored against {args.poses or 'the dataset poses'}, "
             f"{len(frames)} queries"), "",
             f"| map | tail | final training loss | regressor {head} | median |",
             "|---" * 5 + "|"]
    for map_dir in args.maps:
        for name in args.tails:
            scene_map = SceneMap.load(map_dir)
            loss = scene_map.meta["train"]["final_loss_m"]
            if TAILS[name] is not None:
                torch.set_num_threads(2)
                db = scene_map.database
                stats = train_regressor(scene_map.regressor, db.descriptors.astype(np.float32),
                                        db.points, TrainConfig(**TAILS[name]), "cpu",
                                        progress=False, fine_tune=True)
                loss = stats["final_loss_m"]
            torch.set_num_threads(1)
            if feats is None:  # every map is checked to share the first one's features
                feats, _ = query_features(frames, scene_map)
                features = scene_map.meta["features"]
            if scene_map.meta["features"] != features:
                raise SystemExit(f"{map_dir}: other features than {args.maps[0]}")
            lines.append(f"| {map_dir.name} | {name} | {1000 * loss:.1f} mm | "
                         + score_method(scene_map, "regressor", frames, feats) + " |")
            print(lines[-1], flush=True)
    args.out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
