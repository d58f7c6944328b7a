"""Weight averaging against the spread of training: each seed trained once, scored twice.

    python -m benchmarks.experiments.weight_average MAP DATASET [--poses FILE] [--seeds 0 1 2 3] \
        [--average-tail 0.2] --out average.md

For each seed a fresh regressor (the map's architecture) trains on MAP's labelled database
with today's recipe plus `TrainConfig.average_tail`. The same run gives both rows of a seed:
`last epoch` is the weights after the last epoch (what the recipe without averaging ends
with: averaging does not change the iterates), `averaged x` the mean of the epoch-end weights
over the last fraction x of training (`--average-tail` by `train_regressor` itself,
`--other-tails` alongside it from the same iterates). All are scored with the default
localizer on the dataset's test frames against the poses the map was trained on (the
dataset's, or `--poses`).
Nothing is written to the map. A row per seed, then the medians over seeds.
"""

from __future__ import annotations

import argparse
import copy
import time
from pathlib import Path

import numpy as np
import torch

from benchmarks.label_levers import median_rows, method_errors, query_features, scores, summary
from slamreloc.datasets import load_dataset
from slamreloc.localize.evaluate import THRESHOLDS
from slamreloc.regressor.model import SceneCoordinateRegressor
from slamreloc.regressor.train import TrainConfig, WeightAverage, train_regressor
from slamreloc.map.scene_map import SceneMap


def train_seed(scene_map: SceneMap, seed: int, average_tail: float, other_tails: list[float],
               threads: int, epochs: int = TrainConfig.epochs) -> tuple[dict, dict]:
    """One seed's models by name ("last epoch", "averaged <tail>") and its training stats,
    today's recipe. The model averaged over `average_tail` comes from `train_regressor`
    itself; those over `other_tails` are averaged alongside from the same iterates."""
    config = TrainConfig(epochs=epochs, seed=seed, average_tail=average_tail)
    model = SceneCoordinateRegressor(scene_map.regressor.config)
    others = {tail: WeightAverage(model, epochs, tail) for tail in other_tails}
    models = {}

    def snapshot(epoch: int, _loss: float) -> None:
        for average in others.values():
            average.update(model, epoch)
        if epoch == epochs - 1:
            models["last epoch"] = copy.deepcopy(model).eval()
            for tail, average in others.items():
                models[f"averaged {tail:g}"] = copy.deepcopy(model).eval()
                average.copy_to(models[f"averaged {tail:g}"])

    torch.set_num_threads(threads)
    db = scene_map.database
    t0 = time.perf_counter()
    stats = train_regressor(model, db.descriptors.astype(np.float32), db.points, config,
                            "cpu", progress=False, on_epoch_end=snapshot)
    stats["wall_s"] = time.perf_counter() - t0
    models[f"averaged {average_tail:g}"] = model
    return models, stats


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("map", type=Path, help="a map: its labelled database and architecture")
    ap.add_argument("dataset", type=Path)
    ap.add_argument("--poses", type=Path, default=None)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3])
    ap.add_argument("--average-tail", type=float, default=0.2,
                    help="TrainConfig.average_tail of the training runs")
    ap.add_argument("--other-tails", type=float, nargs="*", default=[0.1, 0.4],
                    help="more averages over the same iterates")
    ap.add_argument("--epochs", type=int, default=TrainConfig.epochs)
    ap.add_argument("--threads", type=int, default=2, help="torch threads for training")
    ap.add_argument("--out", type=Path, default=Path("average.md"))
    args = ap.parse_args()
    frames = load_dataset(args.dataset, args.poses).frames("test")
    scene_map = SceneMap.load(args.map)
    torch.set_num_threads(1)
    feats, _ = query_features(frames, scene_map)
    head = " / ".join(THRESHOLDS)
    lines = [(f"`{args.map}` labels, `{args.dataset}` queries scored against "
              f"{args.poses or 'the dataset poses'}, {len(frames)} queries; `averaged x`: the mean "
              "of the epoch-end weights over the last x of training"), "",
             f"| seed | weights | training s | {head} | median |", "|---" * 5 + "|"]
    rows: dict[str, list[list[float]]] = {}
    for seed in args.seeds:
        models, stats = train_seed(scene_map, seed, args.average_tail, args.other_tails,
                                   args.threads, args.epochs)
        torch.set_num_threads(1)
        for name, model in sorted(models.items(), key=lambda kv: kv[0] != "last epoch"):
            scene_map.regressor = model
            errors = method_errors(scene_map, "regressor", frames, feats)
            rows.setdefault(name, []).append(summary(errors))
            lines.append(f"| {seed} | {name} | {stats['wall_s']:.0f} | {scores(errors)} |")
            print(lines[-1], flush=True)
    lines += median_rows(rows)
    args.out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
