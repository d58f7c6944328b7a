"""Live mapping on RedKitchen (`slam --out` with no prior map): the targets of BENCHMARKS.md,
"SLAM that learns its own map".

    python -m benchmarks.live_map_benchmark DATA --work DIR --offline-map MAP [--stages ...]

DATA: the 7-Scenes RedKitchen folder (seq-01 = frames 0-399, seq-02 = 400-599, with
sfm_pgt/poses.txt); MAP: `slamreloc map DATA --out MAP` (seq-01, the dataset's poses), the
offline baseline of the learned map's recall. Stages (all by default):

- stream: the 600 frames as one stream, no prior map, kidnapped every 40 frames from frame
  400 on: kidnaps, recovered-pose error, false anchors, ATE against both references (SE(3)
  aligned on the session's keyframes' poses), throughput, the learner's share; and the curve of
  when each place (keyframe) became relocalizable by the regressor, from each training round's
  published weights (live_map_curve.png).
- learned: a session on seq-01 only -> MAP1, scored with `evaluate` on seq-02 (never tracked)
  against both references, beside the offline MAP on the same queries.
- multi: seq-02 with `--map MAP1 --out MAP2`, kidnapped every 40 frames: anchoring, kidnaps,
  ATE in MAP1's frame against both references (each moved onto MAP1's keyframes).
- kill: kill -9 at random moments of a live session (seq-01), >= 10 times; the last written
  map must load each time.

Prints markdown tables; writes DIR/live_map_benchmark.json.
"""

from __future__ import annotations

import argparse
import copy
import json
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from benchmarks.run_benchmark import cpu_kind
from slamreloc.cli import jobs
from slamreloc.datasets import load_dataset, read_image
from slamreloc.geometry import read_named_trajectory
from slamreloc.localize.localizer import REGRESSOR_PNP
from slamreloc.localize.pnp import estimate_pose
from slamreloc.geometry import pose_error
from slamreloc.map.scene_map import SceneMap
from slamreloc.slam.events import EventKind
from slamreloc.slam.metrics import ate_rmse

SFM = "sfm_pgt/poses.txt"


class PlaceClock:
    """Records when each keyframe (a place) was added, in the learner's clock (seconds since
    the learner started), and each round's published weights: the regressor curve."""

    name = "place-clock"

    def __init__(self, live):
        self.live, self.added, self.rounds = live, [], []
        live.learner.on_round = lambda r, model: self.rounds.append(
            (r.ended_s, copy.deepcopy(model)))

    def attach(self, backend):
        self.backend = backend

    def on_event(self, event, frame):
        if event.kind == EventKind.NEW_KEYFRAME:
            self.added.append((event.frame, time.perf_counter() - self.live.learner._t0))


def live_session(data: Path, out: Path, report: Path, split: str, kidnap: bool,
                 prior: Path | None = None, clock: bool = False) -> tuple[dict, PlaceClock | None]:
    """One `slam --out` session through the command's own job (plugins built as the CLI
    builds them, plus the place clock when asked)."""
    from slamreloc.slam.events import load_plugin
    from slamreloc.slam.live_map import LiveMap, LiveMapConfig
    from slamreloc.map.meta import DatasetMeta

    plugins, probe = None, None
    if clock:
        dataset = load_dataset(data)
        live = LiveMap(LiveMapConfig(), prior=SceneMap.load(prior) if prior else None)
        recorded = DatasetMeta(root=str(dataset.root.resolve()), kind=dataset.kind, split=split,
                               metric=True, poses="slam")
        probe = PlaceClock(live)
        plugins = [load_plugin("live_mapping", live_map=live, out=out, dataset=recorded),
                   load_plugin("relocalization", localizer=live), probe]
    kw = dict(kidnap_every=40, kidnap_skip=20, kidnap_from=400 if split == "all" else 40) \
        if kidnap else {}
    r = jobs.slam(data, prior, report, split, trajectory=report.with_suffix(".txt"),
                  out=out, plugins=plugins, progress=False, **kw)
    return r, probe


def ate_against(traj: Path, reference: dict, keyframes: set[str]) -> float:
    """ATE RMSE (m) of a TUM trajectory (with its names sidecar) against reference poses by
    name, SE(3)-aligned on the keyframes' poses (the session's own frame)."""
    from slamreloc.geometry import align_poses

    named = read_named_trajectory(traj)
    est = dict(zip(named.names, named.poses))
    common = [n for n in est if n in reference]
    kf = [n for n in common if n in keyframes]
    ref_from_est = align_poses([est[n] for n in kf], [reference[n] for n in kf],
                               with_scale=False).rigid
    return ate_rmse([ref_from_est @ est[n] for n in common], [reference[n] for n in common])


def ate_in_map_frame(traj: Path, map_dir: Path, reference: dict) -> float:
    """ATE RMSE (m) of a TUM trajectory (with its names sidecar) in a learned map's frame: the
    reference poses moved onto the map's own keyframes by one rigid fit (as `slam`'s report
    does with a prior map), not refitted on the trajectory."""
    from slamreloc.geometry import align_poses

    frames = SceneMap.load(map_dir).session_frames()
    common = [n for n in frames if n in reference]
    map_from_ref = align_poses([reference[n] for n in common], [frames[n] for n in common],
                               with_scale=False).rigid
    named = read_named_trajectory(traj)
    pairs = [(p, map_from_ref @ reference[n]) for n, p in zip(named.names, named.poses)
             if n in reference]
    return ate_rmse([p for p, _ in pairs], [t for _, t in pairs])


def references(data: Path) -> dict[str, dict]:
    ds, sfm = load_dataset(data), load_dataset(data, data / SFM)
    return {"dataset": {f.name: f.world_from_cam for f in ds.frames("all")},
            "sfm_pgt": {f.name: f.world_from_cam for f in sfm.frames("all")}}


def regressor_curve(data: Path, probe: PlaceClock, trajectory: Path) -> dict:
    """For each place (keyframe k), the frame after it as a probe, localized by the regressor
    alone (PnP-RANSAC on the regressed points, no database) with each round's weights, scored
    against the session's final trajectory (its own frame): the latency from the place's first
    sighting to the end of the first round that relocalizes it within 5 cm / 5 deg."""
    import torch

    ds = load_dataset(data)
    frames = ds.frames("all")
    named = read_named_trajectory(trajectory)
    final = dict(zip(named.names, named.poses))
    live_extractor = probe.live.extractor
    index_to_name = {}
    # processed-frame index -> dataset frame: the session processed `kept` frames in order
    from slamreloc.slam.run import kidnap_schedule

    kept, _ = kidnap_schedule(len(frames), 40, 20, 400)
    for i, k in enumerate(kept):
        index_to_name[i] = frames[k]
    latencies, n_places = [], 0
    for frame_index, t_added in probe.added:
        nxt = index_to_name.get(frame_index + 1)
        if nxt is None or nxt.name not in final:
            continue
        n_places += 1
        feats = live_extractor.extract(read_image(nxt.image_path), nxt.camera)
        for ended_s, model in probe.rounds:
            if ended_s < t_added:
                continue
            with torch.inference_mode():
                pts, conf = model.predict(torch.as_tensor(feats.descriptors))
            keep = np.argsort(-conf.numpy())[:max(len(conf) // 2, min(len(conf), 50))]
            est = estimate_pose(feats.keypoints[keep], pts.numpy()[keep].astype(np.float64),
                                nxt.camera.pinhole, REGRESSOR_PNP)
            if est.success:
                dt, dr = pose_error(est.world_from_cam, final[nxt.name])
                if dt <= 0.05 and dr <= 5:
                    latencies.append(ended_s - t_added)
                    break
    lat = np.array(latencies)
    return {"n_places": n_places, "n_relocalized": len(lat),
            "median_latency_s": float(np.median(lat)) if len(lat) else None,
            "p90_latency_s": float(np.percentile(lat, 90)) if len(lat) else None,
            "within_60s": float(np.sum(lat <= 60) / n_places) if n_places else None,
            "latencies_s": [round(float(v), 2) for v in lat]}


def plot_curve(curve: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    lat = np.sort(curve["latencies_s"])
    t = np.linspace(0, max(120, lat.max() if len(lat) else 0), 200)
    frac = [np.sum(lat <= x) / curve["n_places"] for x in t]
    fig, ax = plt.subplots(figsize=(6, 3.5))
    ax.plot(t, frac)
    ax.axvline(60, ls="--", c="grey")
    ax.set_xlabel("seconds since the place was first seen")
    ax.set_ylabel("places relocalized by the regressor")
    ax.set_title("RedKitchen live mapping: when the regressor learns a place")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def cli(*args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "slamreloc.cli", *map(str, args)],
                          capture_output=True, text=True)


def score(map_dir: Path, data: Path, report: Path) -> dict:
    res = cli("evaluate", map_dir, data, "--split", "test", "--reference", data / SFM,
              "--report", report)
    if res.returncode:
        raise RuntimeError(res.stderr)
    r = json.loads(report.read_text())
    ref = next(iter(r["references"].values()))
    return {"dataset_5cm5deg": r["recall"]["5cm5deg"], "sfm_5cm5deg": ref["recall"]["5cm5deg"],
            "dataset_median_m": r["median_translation_m"],
            "sfm_median_m": ref["median_translation_m"]}


def kill_test(data: Path, work: Path, n: int = 10, seed: int = 0) -> dict:
    """kill -9 a live session (seq-01) at random moments; the last written map must load."""
    rng = random.Random(seed)
    loads, written = 0, 0
    out = work / "killed_map"
    for i in range(n):
        proc = subprocess.Popen([sys.executable, "-m", "slamreloc.cli", "slam", str(data),
                                 "--split", "train", "--out", str(out), "--save-every", "5",
                                 "--report", str(work / f"killed_{i}.json")],
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        time.sleep(rng.uniform(20, 70))
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        if (out / "slamreloc_map.json").exists() or any(out.parent.glob(f".{out.name}*")):
            written += 1
            try:
                SceneMap.load(out)
                loads += 1
            except Exception as e:  # noqa: BLE001 - the benchmark reports it
                print(f"kill {i}: the last map does not load: {e}")
    return {"kills": n, "maps_present": written, "maps_loaded": loads}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("data", type=Path)
    ap.add_argument("--work", type=Path, required=True)
    ap.add_argument("--offline-map", type=Path)
    ap.add_argument("--stages", nargs="+", default=["stream", "learned", "multi", "kill"])
    ap.add_argument("--kills", type=int, default=10)
    args = ap.parse_args()
    work, data = args.work, args.data
    work.mkdir(parents=True, exist_ok=True)
    result = {"cpu": cpu_kind()}
    refs = references(data)
    if "stream" in args.stages:
        r, probe = live_session(data, work / "stream_map", work / "stream.json", "all", True,
                                clock=True)
        kf = set(SceneMap.load(work / "stream_map").database.frame_names)
        curve = regressor_curve(data, probe, work / "stream.txt")
        plot_curve(curve, work / "live_map_curve.png")
        result["stream"] = {
            **{k: r[k] for k in ("n_frames", "n_kidnaps", "n_recovered", "frames_to_recover",
                                 "median_frames_to_recover", "recovered_median_error_m",
                                 "recovered_median_error_deg", "n_false_anchors",
                                 "ate_rmse_aligned_m", "ate_rmse_odometry_only_aligned_m",
                                 "overall_fps", "backend_fps", "n_loop_closures")},
            "ate_dataset_m": ate_against(work / "stream.txt", refs["dataset"], kf),
            "ate_sfm_m": ate_against(work / "stream.txt", refs["sfm_pgt"], kf),
            "learner_share": r["live_map"]["learner_share"],
            "rounds": r["live_map"]["rounds"], "curve": curve}
        print(json.dumps(result["stream"], indent=1))
    if "learned" in args.stages:
        live_session(data, work / "map1", work / "s1.json", "train", False)
        result["learned"] = {"live": score(work / "map1", data, work / "ev_map1.json")}
        if args.offline_map:
            result["learned"]["offline"] = score(args.offline_map, data,
                                                 work / "ev_offline.json")
        print(json.dumps(result["learned"], indent=1))
    if "multi" in args.stages:
        r, _ = live_session(data, work / "map2", work / "s2.json", "test", True,
                            prior=work / "map1")
        anchors = [e["frame"] for e in r["events"] if e["type"] == "tracking_recovered"]
        result["multi"] = {k: r[k] for k in ("n_frames", "n_kidnaps", "n_recovered",
                                             "frames_to_recover", "n_false_anchors",
                                             "ate_rmse_m", "ate_rmse_odometry_only_m",
                                             "recovered_median_error_m",
                                             "recovered_median_error_deg")}
        result["multi"]["first_anchor_frame"] = anchors[0] if anchors else None
        result["multi"].update({f"ate_{k}_m": ate_in_map_frame(work / "s2.txt", work / "map1", v)
                                for k, v in refs.items()})
        print(json.dumps(result["multi"], indent=1))
    if "kill" in args.stages:
        result["kill"] = kill_test(data, work, args.kills)
        print(json.dumps(result["kill"], indent=1))
    (work / "live_map_benchmark.json").write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
