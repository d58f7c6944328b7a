"""GUI panels: layer toggles, point size, frame slider with play/step, follow-camera and top
view, the selected camera's image, the reports' numbers and the legend."""

from __future__ import annotations

import re
import threading
import time
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

import numpy as np

from slamreloc.geometry import Rigid3
from slamreloc.viewer import colors as palette
from slamreloc.viewer.layers import Geometry, Layer, TrajectoryNodes, wxyz
from slamreloc.viewer.images import read_rgb

PANEL_WIDTH = 320


@dataclass
class PlaybackSource:
    """A sequence the frame slider scrubs: a trajectory, a report's queries, the map's cameras."""

    name: str
    poses: list[Rigid3 | None]
    names: list[str | None]
    errors_m: list[float | None]
    image_paths: list[Path | None]
    note: list[str] = field(default_factory=list)  # per-frame extra text (e.g. "not localized")
    thumbnails: list[np.ndarray | None] = field(default_factory=list)  # when no image file

    def __len__(self) -> int:
        return len(self.poses)


@lru_cache(maxsize=64)
def panel_image(path: Path | None) -> np.ndarray | None:
    return read_rgb(path, PANEL_WIDTH)


def placeholder(height: int = 120) -> np.ndarray:
    return np.full((height, PANEL_WIDTH, 3), 60, np.uint8)


def format_value(v) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    if v is None:
        return "–"
    return md_text(str(v))


MD_SPECIAL = re.compile(r"([\\`*\[\]|~])")


def md_text(text: str) -> str:
    """`text` (a name or value a file gave) shown as itself in markdown: HTML's `&`, `<`, `>`
    as entities (never a tag the panel would render), markdown's own characters escaped (a `|`
    never splits a table cell), line breaks as spaces."""
    text = " ".join(text.splitlines())
    text = text.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;")
    return MD_SPECIAL.sub(r"\\\1", text)


def report_table(data: dict) -> str:
    """A markdown table of a report's numbers (nested objects one level deep; lists counted)."""
    rows = []
    for key, value in data.items():
        if isinstance(value, dict):
            for k, v in value.items():
                if isinstance(v, (int, float, str, bool)) or v is None:
                    rows.append((f"{key}.{k}", format_value(v)))
        elif isinstance(value, list):
            rows.append((key, f"{len(value)} entries"))
        else:
            rows.append((key, format_value(value)))
    body = "\n".join(f"| {md_text(k)} | {v} |" for k, v in rows)
    return f"| value | |\n|---|---|\n{body}\n"


@dataclass
class Playback:
    """The frame slider and what follows it: the current-frame frustum, image, text, camera."""

    server: object
    geometry: Geometry
    sources: list[PlaybackSource]
    source: int = 0
    follow: bool = False
    playing: bool = False
    fps: float = 5.0
    marker: object = None
    marker_layer: Layer | None = None  # its toggle decides whether the marker is shown
    slider: object = None
    image: object = None
    text: object = None
    _thread: threading.Thread | None = None
    _stop: threading.Event = field(default_factory=threading.Event)

    @property
    def current(self) -> PlaybackSource:
        return self.sources[self.source]

    def show(self, index: int) -> None:
        src = self.current
        if not len(src):
            return
        index = int(np.clip(index, 0, len(src) - 1))
        pose = src.poses[index]
        if pose is not None and self.marker is not None:
            self.marker.wxyz, self.marker.position = wxyz(pose), pose.translation
            self.marker.visible = self.marker_layer is None or self.marker_layer.visible
        err = src.errors_m[index]
        lines = [f"**{md_text(src.names[index] or f'frame {index}')}** ({index + 1}/{len(src)})"]
        if err is not None and np.isfinite(err):
            lines.append(f"position error: {100 * err:.1f} cm")
        if src.note and src.note[index]:
            lines.append(src.note[index])  # markdown of this viewer's own
        if self.text is not None:
            self.text.content = "  \n".join(lines)
        if self.image is not None:
            img = panel_image(src.image_paths[index])
            if img is None and src.thumbnails:
                img = src.thumbnails[index]
            self.image.image = img if img is not None else placeholder()
        if self.follow and pose is not None:
            self.follow_pose(pose)

    def follow_pose(self, pose: Rigid3, clients=None) -> None:
        g = self.geometry
        forward = pose.rotation[:, 2]
        eye = pose.translation - forward * g.frustum_scale * 6 + g.up * g.frustum_scale * 2
        for client in (clients or self.server.get_clients().values()):
            with client.atomic():
                client.camera.position = eye
                client.camera.look_at = pose.translation + forward * g.frustum_scale * 4

    def step(self, delta: int) -> None:
        if self.slider is not None and len(self.current):
            self.slider.value = int((self.slider.value + delta) % len(self.current))

    def start(self) -> None:
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, daemon=True, name="viewer-play")
            self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            if self.playing:
                self.step(1)
            self._stop.wait(1.0 / max(self.fps, 0.1))

    def stop(self) -> None:
        self._stop.set()


def horizontal_axis(up: np.ndarray) -> np.ndarray:
    """A unit vector perpendicular to `up` (the map's horizontal x axis for the views)."""
    side = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    return side / np.linalg.norm(side)


def top_view(server, g: Geometry, clients=None) -> None:
    eye = g.center + g.up * g.extent * 1.1 + horizontal_axis(g.up) * g.extent * 0.02
    for client in (clients or server.get_clients().values()):
        with client.atomic():
            client.camera.up_direction = g.up
            client.camera.position = eye
            client.camera.look_at = g.center


def orbit_pose(g: Geometry, azimuth_deg: float, elevation_deg: float, distance: float,
               target_offset=(0.0, 0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    """(eye, target): the map's centre (plus an offset, metres) seen from `distance` map
    extents away, at an azimuth around the up axis (0: along `horizontal_axis`) and an
    elevation above the horizontal (degrees)."""
    up = np.asarray(g.up, float)
    x = horizontal_axis(up)
    y = np.cross(up, x)
    az, el = np.radians(azimuth_deg), np.radians(elevation_deg)
    direction = np.cos(el) * (np.cos(az) * x + np.sin(az) * y) + np.sin(el) * up
    target = np.asarray(g.center, float) + np.asarray(target_offset, float)
    return target + direction * g.extent * distance, target


def overview_pose(g: Geometry) -> tuple[np.ndarray, np.ndarray]:
    """(eye, target) of the initial view: above and to the side of the map (0.6 extents
    out, 0.45 up), looking at it."""
    return orbit_pose(g, 0.0, np.degrees(np.arctan2(0.45, 0.6)), 0.75)


def add_layer_toggles(server, layers: list[Layer], trajectories: list[TrajectoryNodes],
                      point_nodes: list) -> dict:
    controls = {}
    with server.gui.add_folder("Layers"):
        for layer in layers:
            box = server.gui.add_checkbox(layer.name, layer.visible)
            box.on_update(lambda _, layer=layer, box=box: layer.set_visible(box.value))
            controls[f"layer:{layer.name}"] = box
        with_error = [t for t in trajectories if t.by_error is not None]
        if with_error:
            box = server.gui.add_checkbox("colour estimates by error", False,
                                          hint="estimate trajectories: red, or by position "
                                               "error against the ground truth")

            def recolour(_):
                for t in with_error:
                    on = t.plain.visible
                    t.plain.nodes[0].visible = on and not box.value
                    t.by_error.visible = on and box.value
            box.on_update(recolour)
            for t in with_error:  # a layer toggle must respect the colouring choice
                t.plain.set_visible = (lambda v, t=t: (
                    setattr(t.plain, "visible", v),
                    setattr(t.plain.nodes[0], "visible", v and not box.value),
                    setattr(t.by_error, "visible", v and box.value)))
            controls["error_colours"] = box
        base = {id(n): n.point_size for n in point_nodes}
        size = server.gui.add_slider("point size", 0.2, 5.0, 0.1, 1.0,
                                     hint="multiple of the default point size")

        def resize(_):
            for n in point_nodes:
                n.point_size = base[id(n)] * size.value
        size.on_update(resize)
        controls["point_size"] = size
    return controls


def add_legend(server, items: list[tuple[str, tuple[int, int, int]]], with_errors: bool):
    with server.gui.add_folder("Legend", expand_by_default=False):
        server.gui.add_html(palette.swatches_html(items))
        if with_errors:
            server.gui.add_html(palette.error_legend_html())


def add_reports_panel(server, reports: list[tuple[str, Path, dict]]) -> list:
    handles = []
    if not reports:
        return handles
    with server.gui.add_folder("Reports", expand_by_default=False):
        for kind, path, data in reports:
            with server.gui.add_folder(f"{kind}: {path.name}", expand_by_default=False):
                handles.append(server.gui.add_markdown(report_table(data)))
    return handles


def add_playback(server, playback: Playback) -> dict:
    c = {}
    with server.gui.add_folder("Frames"):
        if len(playback.sources) > 1:
            c["source"] = server.gui.add_dropdown(
                "sequence", [s.name for s in playback.sources],
                initial_value=playback.sources[0].name)
        n = max(len(playback.current), 1)
        c["slider"] = playback.slider = server.gui.add_slider("frame", 0, max(n - 1, 1), 1, 0,
                                                              disabled=n < 2)
        c["prev"] = server.gui.add_button("◀ step back")
        c["next"] = server.gui.add_button("step ▶")
        c["play"] = server.gui.add_checkbox("play", False)
        c["fps"] = server.gui.add_slider("frames per second", 1, 30, 1, 5)
        c["follow"] = server.gui.add_checkbox("follow camera", False)
        c["top"] = server.gui.add_button("top view")
        c["text"] = playback.text = server.gui.add_markdown("")
        c["image"] = playback.image = server.gui.add_image(placeholder(), label="frame image",
                                                           format="jpeg")

    c["slider"].on_update(lambda _: playback.show(c["slider"].value))
    c["prev"].on_click(lambda _: playback.step(-1))
    c["next"].on_click(lambda _: playback.step(1))
    c["play"].on_update(lambda _: setattr(playback, "playing", c["play"].value))
    c["fps"].on_update(lambda _: setattr(playback, "fps", float(c["fps"].value)))

    def follow(_):
        playback.follow = c["follow"].value
        if playback.follow:
            playback.show(c["slider"].value)
    c["follow"].on_update(follow)
    c["top"].on_click(lambda event: (c["follow"].__setattr__("value", False),
                                     top_view(server, playback.geometry)))
    if "source" in c:
        def switch(_):
            playback.source = [s.name for s in playback.sources].index(c["source"].value)
            n = len(playback.current)
            playback.slider.max = max(n - 1, 1)
            playback.slider.disabled = n < 2
            playback.slider.value = 0
            playback.show(0)
        c["source"].on_update(switch)
    playback.show(0)
    playback.start()
    return c


@dataclass
class Selection:
    """The clicked camera: its name, image and errors in a panel."""

    text: object
    image: object

    def show(self, name: str, image_path: Path | None, extra: str = "",
             thumbnail: np.ndarray | None = None) -> None:
        self.text.content = f"**{md_text(name)}**" + (f"  \n{extra}" if extra else "")
        img = panel_image(image_path)
        if img is None:
            img = thumbnail
        self.image.image = img if img is not None else placeholder()
        self.image.visible = True


def add_selection(server) -> Selection:
    with server.gui.add_folder("Selected camera"):
        text = server.gui.add_markdown("click a camera frustum or a query")
        image = server.gui.add_image(placeholder(), label="selected image", format="jpeg",
                                     visible=False)
    return Selection(text, image)


def snap_to(client, pose: Rigid3, g: Geometry) -> None:
    """Move a client's view onto a camera (slightly behind it, looking where it looks)."""
    forward = pose.rotation[:, 2]
    with client.atomic():
        client.camera.position = pose.translation - forward * g.frustum_scale * 1.5
        client.camera.look_at = pose.translation + forward * g.frustum_scale * 4


def wait_forever(stop: threading.Event) -> None:  # pragma: no cover - interactive
    while not stop.is_set():
        time.sleep(0.5)
