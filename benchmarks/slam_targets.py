"""Issue 8's relocalization targets in one table: `slamreloc slam` with and without kidnapping,
with and without 20 % of the relocalizations replaced by wrong poses (the test harness's
`FaultInjectingRelocalization`, tests/fault_injection.py). From the repository root:

    python -m benchmarks.slam_targets ../shared/data/7scenes_redkitchen --map M [--out T.md]
        [--votes V] [--loop-closure-every K]

Each run is what `slamreloc slam ... --report R --trajectory T` runs, with the default backend
and plugin settings; each run's report and TUM trajectory are written beside --out (for evo).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from slamreloc.cli import jobs
from slamreloc.plugins.gating import GateConfig
from slamreloc.plugins.relocalization import RelocalizationConfig
from tests.fault_injection import FaultInjectingRelocalization

RUNS = {"no kidnapping": (0, 0.0), "--kidnap-every 40": (40, 0.0),
        "no kidnapping, 20 % wrong relocalizations injected": (0, 0.2),
        "--kidnap-every 40 + 20 % injected": (40, 0.2)}


def cm(v) -> str:
    return "-" if v is None else f"{100 * v:.2f} cm"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("dataset", type=Path)
    ap.add_argument("--map", type=Path, required=True)
    ap.add_argument("--out", type=Path, default=Path("slam_targets.md"))
    ap.add_argument("--votes", type=int, default=GateConfig.votes,
                    help="agreeing relocalizations needed to (re-)anchor")
    ap.add_argument("--loop-closure-every", type=int,
                    default=RelocalizationConfig.loop_closure_every,
                    help="keyframes from an accepted relocalization to the next try")
    args = ap.parse_args()
    config = RelocalizationConfig(gate=GateConfig(votes=args.votes),
                                  loop_closure_every=args.loop_closure_every)
    lines = ["| run | ATE map frame | ATE SE(3)-aligned | ATE odometry only | kidnaps recovered "
             "| frames to recover (median; each) | recovered pose error (median) | loop closures "
             "(rejected) | injected (rejected) | false anchors | backend fps |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for k, (name, (every, inject)) in enumerate(RUNS.items()):
        stem = args.out.with_name(f"{args.out.stem}_run{k}")
        faulty = [FaultInjectingRelocalization(args.map, config=config,
                                               wrong_fraction=inject)] if inject else None
        r = jobs.slam(args.dataset, args.map, stem.with_suffix(".json"), kidnap_every=every,
                      trajectory=stem.with_suffix(".txt"), progress=False,
                      plugin_options={"config": config}, plugins=faulty)
        s = r["relocalization"]
        rec = "-" if not r["n_kidnaps"] else f"{r['n_recovered']}/{r['n_kidnaps']}"
        frames_rec = ("-" if not r["n_kidnaps"] else
                      f"{r['median_frames_to_recover']:g} ({', '.join(map(str, r['frames_to_recover']))})")
        err = ("-" if r["recovered_median_error_m"] is None else
               f"{cm(r['recovered_median_error_m'])} / {r['recovered_median_error_deg']:.2f} deg")
        lines.append(f"| {name} | {cm(r['ate_rmse_m'])} | {cm(r['ate_rmse_aligned_m'])} | "
                     f"{cm(r['ate_rmse_odometry_only_m'])} | {rec} | {frames_rec} | {err} | "
                     f"{r['n_loop_closures']} ({r['n_loop_closures_rejected']}) | "
                     f"{s['n_injected']} ({s['n_injected_rejected']}) | {r['n_false_anchors']} | "
                     f"{r['backend_fps']:.1f} |")
        print(lines[-1], flush=True)
    args.out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
