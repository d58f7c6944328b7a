"""Screenshot of `slamreloc view` on the demo's output, for the README (docs/viewer.png).

    slamreloc demo --workdir /tmp/demo-view --no-viewer
    python -m scripts.viewer_screenshot /tmp/demo-view --out docs/viewer.png   (from the
        repository root: it uses tests/browser.py)

Serves the viewer on what the demo wrote (the same inputs `slamreloc demo` serves: map, scene,
reports, trajectories), puts the frame slider on one frame of the SLAM trajectory, opens the
page in headless Chromium (software WebGL), waits until the scene has rendered and saves the
page as a palette PNG (256 colours) to keep it small."""

from __future__ import annotations

import argparse
import io
import sys
import time
from pathlib import Path

import numpy as np

from slamreloc.cli.demo import demo_viewer_inputs
from slamreloc.viewer.gui import orbit_pose
from slamreloc.viewer.server import start
from tests.browser import (chromium_context, decode_png, dismiss_notifications, drawn_fraction,
                           wait_rendered)


def pick_frame(handles, source_prefix: str, frame: int | None) -> str | None:
    """Put the frame slider on `frame` of the first source whose label starts with the prefix
    (default: the middle frame). Returns the source's label."""
    playback = handles.playback
    if playback is None:
        return None
    labels = [s.name for s in playback.sources]
    match = next((i for i, label in enumerate(labels) if label.startswith(source_prefix)), None)
    if match is None:
        return None
    handles.controls["source"].value = labels[match]
    n = len(playback.sources[match])
    handles.controls["slider"].value = n // 2 if frame is None else int(np.clip(frame, 0, n - 1))
    return labels[match]


def save_png(rgb: np.ndarray, out: Path, colours: int) -> int:
    """Write `rgb` as an optimised palette PNG; returns its size in bytes."""
    from PIL import Image

    img = Image.fromarray(rgb).quantize(colours, method=Image.Quantize.MEDIANCUT,
                                        dither=Image.Dither.NONE)
    buf = io.BytesIO()
    img.save(buf, format="PNG", optimize=True)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_bytes(buf.getvalue())
    return len(buf.getvalue())


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("workdir", type=Path, help="what `slamreloc demo --workdir` wrote")
    ap.add_argument("--out", type=Path, default=Path("docs/viewer.png"))
    ap.add_argument("--port", type=int, default=8095)
    ap.add_argument("--size", type=int, nargs=2, default=(1440, 900), metavar=("W", "H"))
    ap.add_argument("--azimuth", type=float, default=-60.0, help="degrees around the up axis")
    ap.add_argument("--elevation", type=float, default=50.0, help="degrees above horizontal")
    ap.add_argument("--distance", type=float, default=0.9, help="in map extents")
    ap.add_argument("--target-offset", type=float, nargs=3, default=(0.0, 0.0, 0.0))
    ap.add_argument("--source", default="estimate: trajectory_slam",
                    help="frame slider source (label prefix)")
    ap.add_argument("--frame", type=int, default=None, help="frame slider position")
    ap.add_argument("--expand", nargs="*", default=["Legend"],
                    help="GUI folders to open besides the default ones")
    ap.add_argument("--colours", type=int, default=256)
    args = ap.parse_args()

    work = args.workdir
    if not (work / "map").is_dir() or not (work / "scene").is_dir():
        print(f"error: {work}: not a demo output (run slamreloc demo --workdir {work})",
              file=sys.stderr)
        return 2
    inputs = demo_viewer_inputs(work, work / "map", work / "scene", args.port)
    t0 = time.perf_counter()
    server, handles = start(inputs)
    print(f"viewer built in {time.perf_counter() - t0:.1f} s: {len(handles.layers)} layers, "
          f"{len(server.scene._handle_from_node_name)} nodes")
    try:
        eye, target = orbit_pose(handles.geometry, args.azimuth, args.elevation, args.distance,
                                 args.target_offset)
        server.initial_camera.position = tuple(eye)
        server.initial_camera.look_at = tuple(target)
        print(f"frame slider: {pick_frame(handles, args.source, args.frame)}")
        width, height = args.size
        with chromium_context(viewport={"width": width, "height": height}) as ctx:
            page = ctx.new_page()
            page.goto(f"http://127.0.0.1:{server.get_port()}")
            page.wait_for_selector("canvas", timeout=60_000)
            dismiss_notifications(page)
            for name in args.expand:
                page.get_by_text(name, exact=True).first.click(timeout=10_000)
            wait_rendered(page, timeout=180, width=width - 420)
            dismiss_notifications(page)  # the software-WebGL one may come late
            time.sleep(1.0)
            shot = decode_png(page.screenshot(timeout=120_000))
        size = save_png(shot, args.out, args.colours)
        print(f"{args.out}: {width}x{height}, {size / 1024:.0f} KB, "
              f"drawn fraction of the view {drawn_fraction(shot[:, :width - 420]):.3f}")
    finally:
        handles.stop()
        server.stop()
    return 0


if __name__ == "__main__":
    sys.exit(main())
