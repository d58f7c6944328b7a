"""Viewer benchmark: a map of N points and F camera frustums, served and opened in headless
Chromium; measures the time from loading the page until the scene is drawn, and the server's
memory.

    python -m benchmarks.viewer_benchmark [--points 500000] [--frustums 1000] [--fresh-browser]
        [--profile] [--out shot.png]          (from the repository root: it uses tests/browser.py)

The map is synthetic (a box-shaped room of coloured points, cameras on a loop with textured
thumbnails), built in memory: what is measured is the viewer, not the map's I/O. The time is
taken inside the page (see PROBE): from the start of the navigation until the first rendered
frame that looks like the final picture."""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import resource
import time
from pathlib import Path

import numpy as np

from slamreloc.geometry import look_at
from slamreloc.types import Camera
from slamreloc.viewer.data import FrameView, MapView, SceneData, ViewerInputs
from tests.browser import canvas_shot, chromium_context, drawn_fraction


def rss_mb() -> float:
    with open(f"/proc/{os.getpid()}/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def synthetic_scene(n_points: int, n_frustums: int, max_images: int = 512,
                    seed: int = 0) -> SceneData:
    rng = np.random.default_rng(seed)
    half = np.array([3.0, 2.5, 1.4])
    face = rng.integers(0, 5, n_points)  # 4 walls + floor
    pts = rng.uniform(-half, half, (n_points, 3))
    axis, sign = np.array([0, 0, 1, 1, 2])[face], np.array([-1, 1, -1, 1, -1])[face]
    pts[np.arange(n_points), axis] = sign * half[axis]
    pts[:, 2] += half[2]
    checker = ((np.floor(pts * 4).astype(int).sum(axis=1)) % 2).astype(np.float64)
    base = np.array([[200, 80, 60], [60, 140, 200], [90, 180, 90], [220, 200, 80],
                     [150, 150, 150]], np.float64)[face]
    colors = np.clip(base * (0.6 + 0.4 * checker[:, None]), 0, 255).astype(np.uint8)
    camera = Camera(640, 480, 525, 525, 319.5, 239.5)
    theta = np.linspace(0, 2 * np.pi, n_frustums, endpoint=False)
    with_image = set(np.linspace(0, n_frustums - 1, min(n_frustums, max_images)).round()
                     .astype(int).tolist())
    frames = []
    for i, t in enumerate(theta):
        eye = np.array([1.8 * np.cos(t), 1.4 * np.sin(t), 1.3 + 0.2 * np.sin(3 * t)])
        pose = look_at(eye, np.array([2.5 * np.cos(t + 0.8), 2.0 * np.sin(t + 0.8), 1.0]))
        thumb = None
        if i in with_image:
            thumb = (rng.integers(0, 255, (15, 20, 3)).repeat(8, 0).repeat(8, 1)).astype(np.uint8)
        frames.append(FrameView(f"frame-{i:06d}", pose, None, thumb))
    scene_map = MapView(Path("synthetic"), pts.astype(np.float32), colors, n_points, "image",
                        frames, camera)
    return SceneData(scene_map, max_images=max_images)


# Page-side timing, injected before the page's own scripts: message batches the websocket worker
# hands to the page (viser decodes the websocket in a Worker), and after each animation-frame
# callback that issued WebGL draw calls, the share of the canvas that is drawn (readPixels of the
# default framebuffer in the same task, so no preserveDrawingBuffer is needed; it waits until the
# frame has really been rasterised). Times: page clock, ms since the navigation started.
PROBE = """
window.__probe = {batches: [], frames: [], drawn: [], dirty: false};
const RealWorker = window.Worker;
window.Worker = function (...args) {
  const w = new RealWorker(...args);
  w.addEventListener("message", (e) => {
    const d = e.data;
    if (d && d.type === "message_batch")
      window.__probe.batches.push([performance.now(), d.messages.length]);
  });
  return w;
};
window.Worker.prototype = RealWorker.prototype;
const G = WebGL2RenderingContext.prototype;
for (const name of ["drawArrays", "drawElements", "drawArraysInstanced", "drawElementsInstanced"]) {
  const real = G[name];
  G[name] = function (...args) { window.__probe.dirty = true; return real.apply(this, args); };
}
function drawnShare(gl) {  // [share of drawn pixels, mean R, G, B of the canvas]
  const w = gl.drawingBufferWidth, h = gl.drawingBufferHeight, px = new Uint8Array(w * h * 4);
  const fb = gl.getParameter(gl.FRAMEBUFFER_BINDING);
  gl.bindFramebuffer(gl.FRAMEBUFFER, null);
  gl.readPixels(0, 0, w, h, gl.RGBA, gl.UNSIGNED_BYTE, px);
  gl.bindFramebuffer(gl.FRAMEBUFFER, fb);
  let n = 0, k = 0, r = 0, g = 0, b = 0;
  for (let i = 0; i < px.length; i += 16, k++) {  // every 4th pixel
    r += px[i]; g += px[i + 1]; b += px[i + 2];
    if (px[i + 3] > 0 && Math.max(255 - px[i], 255 - px[i + 1], 255 - px[i + 2]) > 40) n++;
  }
  return [n / k, r / k, g / k, b / k];
}
const raf = window.requestAnimationFrame.bind(window);
window.requestAnimationFrame = (cb) => raf((t) => {  // t: the frame's time, shared by its callbacks
  const s = performance.now(), probe = window.__probe;
  probe.dirty = false;
  cb(t);
  const d = performance.now() - s, f = probe.frames;
  if (f.length && f[f.length - 1][0] === t) f[f.length - 1][1] += d;
  else f.push([t, d]);
  const canvas = probe.dirty && Array.from(document.querySelectorAll("canvas"))  // the 3D view
    .reduce((a, b) => (b.width * b.height > (a ? a.width * a.height : 0) ? b : a), null);
  const gl = canvas && canvas.getContext("webgl2");
  if (gl) {
    const r = performance.now(), look = drawnShare(gl);
    probe.drawn.push([performance.now(), performance.now() - r, ...look]);
  }
});
"""


def same_look(a: list, b: list) -> bool:
    """Two probe samples show the same picture: drawn share within 0.2 %, mean colour within
    0.5 / 255 per channel."""
    return abs(a[2] - b[2]) < 0.002 and max(abs(x - y) for x, y in zip(a[3:], b[3:])) < 0.5


def page_profile(page, t_drawn_ms: float) -> dict:
    """Where a load's time went, from the probe: when the last message batch arrived, how
    many frames were drawn until the scene was, and their cost (page clock: ms since the
    navigation started)."""
    probe = page.evaluate("window.__probe")
    batches = probe["batches"]
    frames = [(t, d) for t, d in probe["frames"] if t <= t_drawn_ms]
    gaps = np.diff([t for t, _ in frames]) if len(frames) > 1 else np.zeros(1)
    return {"messages": int(sum(n for _, n in batches)), "batches": len(batches),
            "first_batch_s": round(batches[0][0] / 1e3, 2) if batches else None,
            "last_batch_s": round(batches[-1][0] / 1e3, 2) if batches else None,
            "frames_until_drawn": len(frames),
            "frame_js_ms_median": round(float(np.median([d for _, d in frames])), 1)
            if frames else None,
            "frame_gap_ms_median": round(float(np.median(gaps)), 1),
            "frame_gap_ms_max": round(float(gaps.max()), 1)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=500_000)
    ap.add_argument("--frustums", type=int, default=1000)
    ap.add_argument("--port", type=int, default=8090)
    ap.add_argument("--out", type=Path, default=None, help="screenshot (PNG)")
    ap.add_argument("--repeat", type=int, default=3, help="page loads to time")
    ap.add_argument("--max-images", type=int, default=512, help="frustums with a thumbnail")
    ap.add_argument("--fresh-browser", action="store_true",
                    help="start a new browser for each load (default: one browser, new tabs)")
    ap.add_argument("--profile", action="store_true",
                    help="also report message batches and frames per load (page-side probe)")
    args = ap.parse_args()

    from slamreloc.viewer.server import start

    base = rss_mb()
    t0 = time.perf_counter()
    data = synthetic_scene(args.points, args.frustums, args.max_images)
    t_data = time.perf_counter() - t0
    data_mb = rss_mb() - base
    t0 = time.perf_counter()
    server, handles = start(ViewerInputs(Path("synthetic"), port=args.port), data)
    t_build = time.perf_counter() - t0
    url = f"http://127.0.0.1:{server.get_port()}"
    results = {"points": args.points, "frustums": args.frustums,
               "frustums_with_image": sum(f.thumbnail is not None for f in data.map.frames),
               "scene_nodes": len(server.scene._handle_from_node_name),
               "build_scene_s": round(t_build, 2), "make_data_s": round(t_data, 2),
               "rss_before_mb": round(base, 1), "rss_data_mb": round(data_mb, 1),
               "rss_server_mb": round(rss_mb(), 1), "load_s": [],
               "drawn_fraction_screenshot": []}

    def load_once(ctx, k: int) -> None:
        """One page load: until the drawn share of the canvas is stable (page-side probe)."""
        page = ctx.new_page()
        page.add_init_script(PROBE)
        t0 = time.perf_counter()
        page.goto(url)
        drawn = []  # per drawn frame: [t ms, readback ms, share, mean R, G, B]
        while time.perf_counter() - t0 < 120:
            time.sleep(0.2)
            drawn = page.evaluate("window.__probe.drawn")
            if len(drawn) >= 4 and drawn[-1][2] > 0.02 and all(
                    same_look(d, drawn[-1]) for d in drawn[-4:]):
                break
        else:
            raise TimeoutError(f"not drawn within 120 s: {drawn[-4:]}")
        t_drawn = next(d[0] for d in drawn if same_look(d, drawn[-1]))
        results["load_s"].append(round(t_drawn / 1e3, 2))
        shot = canvas_shot(page, timeout_ms=120_000)
        results["drawn_fraction_screenshot"].append(round(drawn_fraction(shot), 3))
        if args.profile:
            prof = page_profile(page, t_drawn)
            prof["readback_ms_median"] = round(float(np.median([d[1] for d in drawn])), 1)
            prof["drawn"] = [(round(d[0] / 1e3, 2), round(d[2], 3), round(sum(d[3:]), 1))
                             for d in drawn[:30]]
            results.setdefault("profile", []).append(prof)
        if args.out and k == args.repeat - 1:
            page.screenshot(path=str(args.out))
        page.close()

    try:
        with contextlib.ExitStack() as stack:
            shared = None if args.fresh_browser else stack.enter_context(chromium_context())
            for k in range(args.repeat):
                with contextlib.ExitStack() as per_load:
                    ctx = shared or per_load.enter_context(chromium_context())
                    load_once(ctx, k)
        results["rss_after_clients_mb"] = round(rss_mb(), 1)
    finally:
        handles.stop()
        server.stop()
    print(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
