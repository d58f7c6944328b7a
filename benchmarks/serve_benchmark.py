"""The relocalization service against the in-process code, on a real map.

    python -m benchmarks.serve_benchmark ../shared/data/7scenes_redkitchen --map MAP \
        [--split seq-02] [--requests 10000] [--out serve_benchmark.json]

1. Latency: the split's frames as JPEG bytes, one client, `slamreloc serve` in its own process
   (default settings) against in-process `Localizer.localize` on the same bytes (decoding
   included on both sides), rounds interleaved; medians; every pose compared bit for bit.
2. Throughput: a server with `--workers 2`; one client, then 4 concurrent clients sending
   `--requests` in all; requests per second, p50 / p99 latency; every answer must be the pose
   of the image it was sent for (none lost, none answered twice or swapped).
3. Session: `slamreloc slam --kidnap-every 40` against a session over the same frames
   (server odometry on the streamed depth); the recovery numbers side by side.
4. Reload under load: 4 clients while the served map folder is replaced 3 times by the map
   writer; failed requests counted.
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from benchmarks.run_benchmark import cpu_name
from slamreloc.client import Client, RemoteError, confirmed_frames, frame_poses
from slamreloc.datasets import load_dataset
from slamreloc.io.outputs import write_json
from slamreloc.io.images import decode_rgb
from slamreloc.localize.localizer import RegressorLocalizer
from slamreloc.map.format import SURFACE
from slamreloc.map.write import save_map
from slamreloc.proto import relocalizer_pb2 as pb
from slamreloc.proto.messages import transform_msg
from slamreloc.map.scene_map import SceneMap
from slamreloc.slam.feed import depth_camera_of, read_frames
from slamreloc.slam.report import kidnap_stats
from slamreloc.slam.run import kidnap_schedule


class Server:
    """`slamreloc serve` in a child process."""

    def __init__(self, maps: list[Path], *args: str):
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "slamreloc.cli", "serve", *map(str, maps), "--port", "0",
             *args], stdout=subprocess.PIPE, text=True)
        line = self.proc.stdout.readline()
        if "listening on" not in line:
            raise RuntimeError(f"server did not start: {line!r}")
        self.address = line.split()[2]

    def stop(self) -> None:
        self.proc.terminate()
        self.proc.wait(timeout=60)


def pct(values, q):
    return float(np.percentile(values, q)) if values else None


def key(response: pb.LocalizeResponse) -> bytes:
    return response.world_from_cam.SerializeToString() + bytes([response.localized])


def latency(map_dir: Path, jpegs: list[bytes], rounds: int) -> dict:
    scene_map = SceneMap.load(map_dir)
    loc = RegressorLocalizer(scene_map)
    server = Server([map_dir])
    local_ms, remote_ms, mismatched = [], [], 0
    try:
        with Client(server.address) as client:
            for data in jpegs[:5]:  # warm-up: first-call kernel compilation on both sides
                client.localize(data)
                loc.localize(decode_rgb(data, "q"), scene_map.camera.scaled_to(640, 480))
            # rounds alternate whole passes (A B A B): an idle process's OpenMP threads spin
            # for a while after its last call and would slow the other side of a per-frame
            # interleaving
            local_poses, remote_poses = [], []
            for _ in range(rounds):
                for data in jpegs:
                    t0 = time.perf_counter()
                    image = decode_rgb(data, "q")
                    h, w = image.shape[:2]
                    est = loc.localize(image, scene_map.camera.scaled_to(w, h)).estimate
                    local_ms.append(1000 * (time.perf_counter() - t0))
                    local_poses.append(None if est.world_from_cam is None
                                       else transform_msg(est.world_from_cam))
                for data in jpegs:
                    t0 = time.perf_counter()
                    answer = client.localize(data)
                    remote_ms.append(1000 * (time.perf_counter() - t0))
                    remote_poses.append(answer.response.world_from_cam
                                        if answer.response.HasField("world_from_cam") else None)
            mismatched = sum(a != b for a, b in zip(local_poses, remote_poses))
    finally:
        server.stop()
    local, remote = statistics.median(local_ms), statistics.median(remote_ms)
    return {"frames": len(jpegs), "rounds": rounds, "in_process_median_ms": round(local, 2),
            "service_median_ms": round(remote, 2), "ratio": round(remote / local, 3),
            "poses_not_bit_identical": mismatched}


class Load:
    """`total` requests of the images in turn from `n_clients` client threads; every answer
    checked against `expected` (the pose of the image it was sent for)."""

    def __init__(self, address: str, jpegs: list[bytes], expected: list[bytes], total: int):
        self.address, self.jpegs, self.expected = address, jpegs, expected
        self.todo = iter(range(total))
        self.lock = threading.Lock()
        self.latency_ms: list[float] = []
        self.answered = self.failed = self.wrong = 0

    def client(self) -> None:
        with Client(self.address) as client:
            while True:
                with self.lock:
                    i = next(self.todo, None)
                if i is None:
                    return
                t0 = time.perf_counter()
                try:
                    r = client.localize(self.jpegs[i % len(self.jpegs)]).response
                except RemoteError:
                    with self.lock:
                        self.failed += 1
                    continue
                ms = 1000 * (time.perf_counter() - t0)
                with self.lock:
                    self.latency_ms.append(ms)
                    self.answered += 1
                    self.wrong += key(r) != self.expected[i % len(self.jpegs)]

    def run(self, n_clients: int) -> float:
        t0 = time.perf_counter()
        threads = [threading.Thread(target=self.client) for _ in range(n_clients)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        return time.perf_counter() - t0


def throughput(map_dir: Path, jpegs: list[bytes], n_requests: int) -> dict:
    server = Server([map_dir], "--workers", "2")
    out = {}
    try:
        with Client(server.address) as client:
            expected = [key(client.localize(d).response) for d in jpegs]
        for n_clients in (1, 4):
            total = n_requests if n_clients == 4 else max(n_requests // 10, 4 * len(jpegs))
            load = Load(server.address, jpegs, expected, total)
            wall = load.run(n_clients)
            out[f"{n_clients}_clients"] = {
                "requests": total, "answered": load.answered, "failed": load.failed,
                "wrong_or_swapped": load.wrong, "per_s": round(load.answered / wall, 2),
                "p50_ms": round(pct(load.latency_ms, 50), 1),
                "p99_ms": round(pct(load.latency_ms, 99), 1)}
            print(f"  {n_clients} clients: {out[f'{n_clients}_clients']}", flush=True)
    finally:
        server.stop()
    out["speedup"] = round(out["4_clients"]["per_s"] / out["1_clients"]["per_s"], 2)
    return out


def session(dataset_dir: Path, map_dir: Path, split: str, workdir: Path) -> dict:
    report_path = workdir / "slam.json"
    subprocess.run([sys.executable, "-m", "slamreloc.cli", "slam", str(dataset_dir), "--map",
                    str(map_dir), "--split", split, "--kidnap-every", "40", "--kidnap-skip",
                    "20", "--report", str(report_path)], check=True, stdout=subprocess.DEVNULL)
    report = json.loads(report_path.read_text())
    dataset = load_dataset(dataset_dir)
    all_frames = dataset.frames(split)
    kept, jumps = kidnap_schedule(len(all_frames), 40, 20)
    frames = [all_frames[i] for i in kept]
    server = Server([map_dir])
    results = []
    t0 = time.perf_counter()
    try:
        with Client(server.address) as client:
            depth_camera = depth_camera_of(frames)
            with client.session(odometry="auto", depth_camera=depth_camera) as s:
                for inp in read_frames(dataset, frames):
                    results.append(s.send(inp.image, camera=inp.camera, depth=inp.depth,
                                          timestamp=inp.timestamp))
    finally:
        server.stop()
    wall = time.perf_counter() - t0
    ours = kidnap_stats(confirmed_frames(results), frame_poses(results),
                        [f.world_from_cam for f in frames], jumps)
    keys = ("n_kidnaps", "n_recovered", "frames_to_recover", "recovered_median_error_m",
            "recovered_median_error_deg")
    return {"slam": {k: report[k] for k in keys}, "session": {k: ours[k] for k in keys},
            "session_fps": round(len(frames) / wall, 2), "frames": len(frames)}


def reload_under_load(map_dir: Path, jpegs: list[bytes], workdir: Path) -> dict:
    served = workdir / "served"
    shutil.copytree(map_dir, served)
    server = Server([served], "--workers", "2", "--watch", "0.2")
    stop, answered, failed, versions = threading.Event(), [0], [], set()
    lock = threading.Lock()

    def worker(j):
        with Client(server.address) as client:
            i = j
            while not stop.is_set():
                try:
                    r = client.localize(jpegs[i % len(jpegs)]).response
                    with lock:
                        answered[0] += 1
                        versions.add(r.map_version)
                except RemoteError as err:
                    failed.append(str(err))
                i += 1

    threads = [threading.Thread(target=worker, args=(j,)) for j in range(4)]
    for t in threads:
        t.start()
    try:
        scene_map = SceneMap.load(served)
        with Client(server.address) as client:
            seen = [client.list_maps()[0].version]
            for i in range(3):
                time.sleep(2)
                meta = replace(scene_map.info, timings_s={**scene_map.info.timings_s,
                                                          "reload_benchmark": float(i)})
                extra = ({SURFACE: scene_map.surface.to_arrays()}
                         if scene_map.surface is not None else None)
                save_map(served, meta, scene_map.regressor, scene_map.database, extra=extra)
                deadline = time.time() + 60
                while client.list_maps()[0].version == seen[-1] and time.time() < deadline:
                    time.sleep(0.1)
                seen.append(client.list_maps()[0].version)
            time.sleep(2)
    finally:
        stop.set()
        for t in threads:
            t.join()
        server.stop()
    return {"replacements": 3, "versions_served": len(seen), "answered": answered[0],
            "failed": len(failed), "versions_in_answers": len(versions)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset", type=Path)
    ap.add_argument("--map", type=Path, required=True)
    ap.add_argument("--split", default="seq-02")
    ap.add_argument("--frames", type=int, default=40, help="frames in the latency test")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--requests", type=int, default=10000)
    ap.add_argument("--only", default="latency,throughput,session,reload")
    ap.add_argument("--out", type=Path, default=Path("serve_benchmark.json"))
    args = ap.parse_args()
    frames = load_dataset(args.dataset).frames(args.split)
    step = max(1, len(frames) // args.frames)
    jpegs = [cv2.imencode(".jpg", cv2.imread(str(f.image_path)),
                          [cv2.IMWRITE_JPEG_QUALITY, 95])[1].tobytes()
             for f in frames[::step][:args.frames]]
    result = {"cpu": cpu_name(), "map": str(args.map), "split": args.split}
    only = args.only.split(",")
    with tempfile.TemporaryDirectory() as tmp:
        if "latency" in only:
            result["latency"] = latency(args.map, jpegs, args.rounds)
            print("latency", result["latency"], flush=True)
        if "throughput" in only:
            result["throughput"] = throughput(args.map, jpegs, args.requests)
            print("throughput", result["throughput"], flush=True)
        if "session" in only:
            result["session"] = session(args.dataset, args.map, args.split, Path(tmp))
            print("session", result["session"], flush=True)
        if "reload" in only:
            result["reload"] = reload_under_load(args.map, jpegs, Path(tmp))
            print("reload", result["reload"], flush=True)
    write_json(args.out, result)


if __name__ == "__main__":
    main()
