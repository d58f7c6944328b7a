"""Memory of `slamreloc localize` on normal and hostile images (BENCHMARKS.md, "Input bounds").

    python -m benchmarks.input_bounds MAP QUERY.png [--runs 5] [--baseline-pythonpath DIR]

Runs `slamreloc localize MAP IMAGE` as a whole process and reads its peak resident memory from
the kernel (wait4's ru_maxrss), for:
- the normal query (QUERY, e.g. a 640x480 RedKitchen frame): median of --runs; with
  --baseline-pythonpath (another slamreloc installed with `pip install --target DIR`) the two
  run in turn, A B A B, and their medians are compared;
- hostile images made here: a 1.2 MB PNG whose header claims 20000 x 20000, a JPEG claiming
  65000 x 65000, and the largest image the bounds let through for MAP's extractor (and one a
  little larger), each under a 3 GB address-space cap.
"""

from __future__ import annotations

import argparse
import os
import resource
import statistics
import struct
import subprocess
import sys
import tempfile
import time
import zlib
from pathlib import Path

import cv2
import numpy as np

CAP = 3 << 30


def run(argv: list[str], pythonpath: str | None = None) -> tuple[int, float, float, str]:
    """(exit status, peak RSS MB, wall s, last stderr line) of one whole-process run."""
    env = dict(os.environ)
    if pythonpath:
        env["PYTHONPATH"] = pythonpath
    code = "import sys; from slamreloc.cli import main; sys.argv[0] = 'slamreloc'; main()"

    def cap():
        resource.setrlimit(resource.RLIMIT_AS, (CAP, CAP))

    t0 = time.perf_counter()
    with tempfile.TemporaryFile() as err:
        proc = subprocess.Popen([sys.executable, "-c", code, *argv], stdout=subprocess.DEVNULL,
                                stderr=err, env=env, preexec_fn=cap)
        _, status, usage = os.wait4(proc.pid, 0)
        proc.returncode = 0
        wall = time.perf_counter() - t0
        err.seek(0)
        lines = err.read().decode(errors="replace").strip().splitlines()
    return (os.waitstatus_to_exitcode(status), usage.ru_maxrss / 1024, wall,
            lines[-1][:160] if lines else "")


def png_bomb(path: Path, side: int = 20000) -> None:
    def chunk(kind: bytes, payload: bytes) -> bytes:
        return (struct.pack(">I", len(payload)) + kind + payload
                + struct.pack(">I", zlib.crc32(kind + payload)))

    comp, row, data = zlib.compressobj(9), b"\x00" * (1 + 3 * side), b""
    for _ in range(side):  # every row present: a valid 20000 x 20000 RGB image of 1.2 MB
        data += comp.compress(row)
    data += comp.flush()
    path.write_bytes(b"\x89PNG\r\n\x1a\n"
                     + chunk(b"IHDR", struct.pack(">IIBBBBB", side, side, 8, 2, 0, 0, 0))
                     + chunk(b"IDAT", data) + chunk(b"IEND", b""))


def jpeg_bomb(path: Path, side: int = 65000) -> None:
    data = bytearray(cv2.imencode(".jpg", np.full((16, 16, 3), 128, np.uint8))[1].tobytes())
    sof = data.index(b"\xff\xc0")
    data[sof + 5:sof + 9] = struct.pack(">HH", side, side)
    path.write_bytes(bytes(data))


def largest_allowed(map_dir: Path) -> int:
    """The side of the largest square image the bounds let MAP's extractor take."""
    from slamreloc.features import make_extractor
    from slamreloc.io.limits import limits
    from slamreloc.map.scene_map import SceneMap

    info = SceneMap.load(map_dir, regressor=False).info
    ex = make_extractor(info.feature_name, **info.feature_options)
    per_pixel = ex.working_pixels(1, 1) * ex.bytes_per_pixel
    lim = limits()
    return int(min(lim.max_image_pixels, lim.max_feature_bytes / per_pixel) ** 0.5)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("map", type=Path)
    ap.add_argument("query", type=Path)
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--baseline-pythonpath")
    args = ap.parse_args()

    print(f"CPU: {cpu_name()}")
    base = ["localize", str(args.map)]
    new, old = [], []
    for _ in range(args.runs):
        new.append(run(base + [str(args.query)]))
        if args.baseline_pythonpath:
            old.append(run(base + [str(args.query)], args.baseline_pythonpath))
    rows = [("normal query, this code", new)]
    if old:
        rows.append(("normal query, baseline", old))
    print("\n| input | exit | peak RSS MB (median, min-max) | wall s (median) |")
    print("|---|---|---|---|")
    for name, runs in rows:
        rss = [r[1] for r in runs]
        print(f"| {name} | {runs[0][0]} | {statistics.median(rss):.0f} ({min(rss):.0f}-"
              f"{max(rss):.0f}) | {statistics.median(r[2] for r in runs):.2f} |")

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        png_bomb(tmp / "bomb.png")
        jpeg_bomb(tmp / "bomb.jpg")
        side = largest_allowed(args.map)
        rng = np.random.default_rng(0)
        texture = (rng.random((side // 8, side // 8)) * 255).astype(np.uint8)
        img = cv2.resize(texture, (side, side), interpolation=cv2.INTER_LINEAR)
        cv2.imwrite(str(tmp / "at_bound.png"), img)
        cv2.imwrite(str(tmp / "over_bound.png"), cv2.resize(img, (side + 16, side + 16)))
        for name in ("bomb.png", "bomb.jpg", "at_bound.png", "over_bound.png"):
            size = (tmp / name).stat().st_size
            code, rss, wall, err = run(base + [str(tmp / name)])
            print(f"| {name} ({size / 1e6:.2f} MB file) | {code} | {rss:.0f} | {wall:.2f} | "
                  f"{err.replace('|', '/')} |")
    print(f"\nlargest square image the bounds allow for this map: {side} x {side}")


def cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                flags = Path("/proc/cpuinfo").read_text()
                kind = ("AMX" if " amx" in flags else "AVX512-BF16" if "avx512_bf16" in flags
                        else "AVX2")
                return f"{line.split(':', 1)[1].strip()} ({kind}, {os.cpu_count()} cores)"
    except OSError:
        pass
    return "unknown"


if __name__ == "__main__":
    main()
