"""Two regressors per query against the spread of one training: each seed alone, then pairs.

    python -m benchmarks.ensemble MAP DATASET [--poses FILE] [--seeds 0 1 2] \
        [--epochs 100] [--batch-size 1024 --lr 2e-3] [--keep 0.5 1.0] [--no-pairs] [--unguided] \
        [--precision auto|fp32|bf16] [--workdir W] [--matching] --out ensemble.md

Each seed trains a fresh regressor (MAP's architecture, today's recipe) on MAP's labelled
database (`--epochs`, `--batch-size`, `--lr` and `--precision` change today's recipe). The
seed fixes the model, so a seed's weights are kept in
WORKDIR/seed-<s>-epochs-<e>[-batch-<b>-lr-<lr>][-<precision>].pt and reused by a later run.
The database holds float16 descriptors and `slamreloc map` trains on the float32 ones before
storing them, so seed s here is another training than `map`'s seed s.

Rows: each model alone (the spread of one training), then each pair of models combined per
keypoint, scored with the default localizer (its confident half, PnP-RANSAC, refinement):
- `mean`: the average of the two predicted points, confidence the mean of the two;
- `confident`: the point of the model more confident about that keypoint;
- `agree`: the average where the two points lie within `--agree-m` of each other, otherwise
  the more confident model's point at half its confidence.
`--keep` adds rows for each model alone with PnP on another share of its predictions (the
localizer's `keep_fraction`; the default localizer keeps 0.5); `--unguided` adds rows for each
model alone without the guided refinement (the pose RANSAC's on the regressed points, as
before 2026-12-04); `--no-pairs` leaves the pairs out. The last line counts the queries that all, some or none of the single models put within
1 cm / 1 deg, and the errors of those they dispute. A pair costs two forward passes: about
twice one model's regressor time per query (the `regressor ms` column, one torch thread,
median over queries). Scored against the poses the map was trained on (the dataset's, or
`--poses`). Nothing is written to the map.
"""

from __future__ import annotations

import argparse
import itertools
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
from torch import nn

from benchmarks.label_levers import median_rows, method_errors, query_features, scores, summary
from slamreloc.localize import evaluate
from slamreloc.datasets import load_dataset
from slamreloc.localize.evaluate import THRESHOLDS
from slamreloc.localize.localizer import make_localizer
from slamreloc.regressor.model import SceneCoordinateRegressor
from slamreloc.regressor.train import TrainConfig, train_regressor
from slamreloc.map.scene_map import SceneMap

COMBINATIONS = ("mean", "confident", "agree")


class PairedRegressor(nn.Module):
    """Two trained regressors answering as one (`predict` as SceneCoordinateRegressor's:
    world points in metres and a confidence in [0, 1] per descriptor)."""

    def __init__(self, a: SceneCoordinateRegressor, b: SceneCoordinateRegressor,
                 combination: str, agree_m: float = 0.05) -> None:
        super().__init__()
        if combination not in COMBINATIONS:
            raise ValueError(f"unknown combination '{combination}' (known: {COMBINATIONS})")
        self.a, self.b, self.combination, self.agree_m = a, b, combination, agree_m

    def predict(self, desc: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        pa, ca = self.a.predict(desc)
        pb, cb = self.b.predict(desc)
        mean = (pa + pb) / 2
        if self.combination == "mean":
            return mean, (ca + cb) / 2
        a_wins = (ca >= cb).unsqueeze(1)
        confident = torch.where(a_wins, pa, pb)
        if self.combination == "confident":
            return confident, torch.maximum(ca, cb)
        agree = (pa - pb).norm(dim=1) < self.agree_m
        return (torch.where(agree.unsqueeze(1), mean, confident),
                torch.where(agree, (ca + cb) / 2, torch.maximum(ca, cb) / 2))


def seed_model(scene_map: SceneMap, seed: int, workdir: Path, threads: int,
               recipe: TrainConfig) -> tuple[SceneCoordinateRegressor, float | None]:
    """The regressor of `seed` on the map's database, and its training wall time (s; None when
    it was loaded from WORKDIR)."""
    model = SceneCoordinateRegressor(scene_map.regressor.config)
    name = f"seed-{seed}-epochs-{recipe.epochs}"
    if (recipe.batch_size, recipe.lr) != (TrainConfig.batch_size, TrainConfig.lr):
        name += f"-batch-{recipe.batch_size}-lr-{recipe.lr:g}"
    if recipe.precision != "auto":
        name += f"-{recipe.precision}"
    path = workdir / f"{name}.pt"
    if path.is_file():
        model.load_state_dict(torch.load(path))
        return model.eval(), None
    torch.set_num_threads(threads)
    db = scene_map.database
    t0 = time.perf_counter()
    train_regressor(model, db.descriptors.astype(np.float32), db.points,
                    replace(recipe, seed=seed), "cpu", progress=True)
    wall_s = time.perf_counter() - t0
    workdir.mkdir(parents=True, exist_ok=True)
    torch.save(model.state_dict(), path)
    return model.eval(), wall_s


def regressor_ms(scene_map: SceneMap, feats) -> float:
    """Median time of the localizer's regressor stage per query (ms)."""
    loc = make_localizer(scene_map, "regressor")
    ms = []
    for f in feats:
        t0 = time.perf_counter()
        loc.predict(f.descriptors)
        ms.append(1000 * (time.perf_counter() - t0))
    return float(np.median(ms))


def verdicts(errors: list[np.ndarray], threshold: str = "1cm1deg") -> str:
    """How many queries each single model puts within `threshold` (evaluate.THRESHOLDS):
    all of them, some of them, none; and the translation errors of the disputed ones."""
    within = np.array([evaluate.within(e[:, 0], e[:, 1])[threshold] for e in errors])
    every, some = within.all(0), within.any(0) & ~within.all(0)
    disputed = np.concatenate([e[some, 0] for e in errors]) * 100
    spread = (f"; their translation errors over the models: median {np.median(disputed):.2f} "
              f"cm, 10-90 % {np.percentile(disputed, 10):.2f}-{np.percentile(disputed, 90):.2f}"
              " cm" if some.any() else "")
    return (f"Within {threshold} for all {len(errors)} single models: {every.sum()} queries; "
            f"for some but not all: {some.sum()}; for none: {(~within.any(0)).sum()}" + spread)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("map", type=Path, help="a map: its labelled database and architecture")
    ap.add_argument("dataset", type=Path)
    ap.add_argument("--poses", type=Path, default=None)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--epochs", type=int, default=TrainConfig.epochs)
    ap.add_argument("--batch-size", type=int, default=TrainConfig.batch_size)
    ap.add_argument("--lr", type=float, default=TrainConfig.lr)
    ap.add_argument("--agree-m", type=float, default=0.05)
    ap.add_argument("--keep", type=float, nargs="+", default=[],
                    help="also score each model alone at these keep fractions")
    ap.add_argument("--no-pairs", action="store_true", help="single models only")
    ap.add_argument("--unguided", action="store_true",
                    help="also score each model alone without the guided refinement")
    ap.add_argument("--threads", type=int, default=2, help="torch threads for training")
    ap.add_argument("--precision", default="auto", help="training precision: auto | fp32 | bf16")
    ap.add_argument("--workdir", type=Path, default=Path("/tmp/slamreloc-ensemble"))
    ap.add_argument("--matching", action="store_true", help="score matching on the map too")
    ap.add_argument("--out", type=Path, default=Path("ensemble.md"))
    args = ap.parse_args()
    frames = load_dataset(args.dataset, args.poses).frames("test")
    scene_map = SceneMap.load(args.map)
    recipe = TrainConfig(epochs=args.epochs, batch_size=args.batch_size, lr=args.lr,
                         precision=args.precision)
    models, lines = {}, []
    for seed in args.seeds:
        models[seed], wall_s = seed_model(scene_map, seed, args.workdir, args.threads, recipe)
        if wall_s is not None:
            print(f"seed {seed}: trained in {wall_s:.0f} s", flush=True)
    torch.set_num_threads(1)
    feats, _ = query_features(frames, scene_map)
    head = " / ".join(THRESHOLDS)
    lines += [(f"`{args.map}` labels, `{args.dataset}` queries scored against "
               f"{args.poses or 'the dataset poses'}, {len(frames)} queries, {args.epochs} "
               f"epochs, batch {args.batch_size}, lr {args.lr:g}; "
               f"`agree` within {100 * args.agree_m:g} cm"), "",
              f"| models | combination | regressor ms | {head} | median |", "|---" * 5 + "|"]
    rows: dict[str, list[list[float]]] = {}

    def score(name: str, combination: str, regressor, **options) -> np.ndarray:
        scene_map.regressor = regressor
        ms = regressor_ms(scene_map, feats)
        errors = method_errors(scene_map, "regressor", frames, feats, **options)
        rows.setdefault(combination, []).append(summary(errors))
        lines.append(f"| {name} | {combination} | {ms:.1f} | {scores(errors)} |")
        print(lines[-1], flush=True)
        return errors

    alone = [score(f"seed {seed}", "alone", model) for seed, model in models.items()]
    for keep in args.keep:
        for seed, model in models.items():
            score(f"seed {seed}", f"alone, keep {keep:g}", model, keep_fraction=keep)
    if args.unguided:
        for seed, model in models.items():
            score(f"seed {seed}", "alone, unguided", model, guided=None)
    pairs = [] if args.no_pairs else itertools.combinations(models.items(), 2)
    for (sa, a), (sb, b) in pairs:
        for combination in COMBINATIONS:
            score(f"seeds {sa} + {sb}", combination, PairedRegressor(a, b, combination,
                                                                      args.agree_m))
    if args.matching:
        errors = method_errors(scene_map, "matching", frames, feats)
        lines.append(f"| matching | | | {scores(errors)} |")
    lines += median_rows(rows) + ["", verdicts(alone)]
    args.out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
