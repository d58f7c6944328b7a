"""`build_scene(server, data)`: every layer and panel on a viser server, without a browser."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from slamreloc.viewer import colors as palette
from slamreloc.viewer import gui, layers
from slamreloc.viewer.data import FrameView, QueryView, SceneData
from slamreloc.viewer.map_view import estimate_up


@dataclass
class SceneHandles:
    server: object
    data: SceneData
    geometry: layers.Geometry
    layers: dict[str, layers.Layer] = field(default_factory=dict)
    trajectories: list[layers.TrajectoryNodes] = field(default_factory=list)
    controls: dict = field(default_factory=dict)
    playback: gui.Playback | None = None
    selection: gui.Selection | None = None
    report_panels: list = field(default_factory=list)

    def add_layer(self, layer: layers.Layer) -> layers.Layer:
        """Register a layer under a unique name (its toggle's label)."""
        base, k = layer.name, 2
        while layer.name in self.layers:
            layer.name, k = f"{base} ({k})", k + 1
        self.layers[layer.name] = layer
        return layer

    def node_names(self) -> list[str]:
        return [n.name for layer in self.layers.values() for n in layer.nodes]

    def stop(self) -> None:
        if self.playback is not None:
            self.playback.stop()


def _sources(data: SceneData) -> list[gui.PlaybackSource]:
    out = []
    for t in data.trajectories:
        err = t.errors_m
        out.append(gui.PlaybackSource(
            f"{t.kind}: {t.name}", list(t.poses),
            [n or f"{t.stamps[i]:.3f}" for i, n in enumerate(t.names)],
            [None if err is None or not np.isfinite(err[i]) else float(err[i])
             for i in range(len(t))],
            list(t.image_paths) or [None] * len(t)))
    for r in data.evaluations:
        q = r.queries
        out.append(gui.PlaybackSource(
            f"queries: {r.path.name}", [x.estimate or x.truth for x in q], [x.name for x in q],
            [x.translation_error_m for x in q], [x.image_path for x in q],
            [_query_note(x) for x in q]))
    frames = [f for f in data.map.frames if f.world_from_cam is not None]
    if frames:
        out.append(gui.PlaybackSource(
            "training cameras", [f.world_from_cam for f in frames], [f.name for f in frames],
            [None] * len(frames), [f.image_path for f in frames],
            thumbnails=[f.thumbnail for f in frames]))
    return out


def _query_note(q: QueryView) -> str:
    if q.failed:
        return "**not localized** (shown where the ground truth is)"
    parts = []
    if q.rotation_error_deg is not None:
        parts.append(f"rotation error: {q.rotation_error_deg:.2f} deg")
    if q.num_inliers is not None:
        parts.append(f"{q.num_inliers} inliers")
    if q.estimate is None:
        parts.append("estimated pose not given (pass evaluate's --trajectory file to the viewer)")
    return ", ".join(parts)


def build_scene(server, data: SceneData) -> SceneHandles:
    """Put the map, cameras, trajectories and reports on `server`; returns the handles."""
    poses = np.array([f.world_from_cam.matrix() for f in data.map.frames
                      if f.world_from_cam is not None]).reshape(-1, 4, 4)
    up = estimate_up(poses)
    g = layers.scene_geometry(data.map, up)
    h = SceneHandles(server, data, g)
    server.scene.set_up_direction(tuple(float(v) for v in up))
    server.scene.world_axes.visible = False
    eye, target = gui.overview_pose(g)
    server.initial_camera.position = tuple(eye)
    server.initial_camera.look_at = tuple(target)
    server.initial_camera.up = tuple(float(v) for v in up)

    def on_frame_click(frame: FrameView, event) -> None:
        h.selection.show(frame.name, frame.image_path, "training camera", frame.thumbnail)
        if event is not None and event.client is not None:
            gui.snap_to(event.client, frame.world_from_cam, g)

    def on_query_click(q: QueryView, event) -> None:
        err = ("not localized" if q.failed else
               f"position error {100 * q.translation_error_m:.1f} cm")
        h.selection.show(q.name, q.image_path, f"query: {err}; {_query_note(q)}")
        if event is not None and event.client is not None and q.estimate is not None:
            gui.snap_to(event.client, q.estimate, g)

    points, added = layers.add_map_points(server, data.map, g)
    h.add_layer(points)
    point_nodes = list(points.nodes)
    if added is not None:
        h.add_layer(added)
        point_nodes += added.nodes
    h.add_layer(layers.add_training_cameras(server, data.map, g, on_frame_click))
    legend = [("map points: image colour" if data.map.color_source == "image"
               else "map points: height", (128, 128, 128)),
              ("training camera", palette.TRAINING_CAMERA)]
    pseudo = layers.add_pseudo_frames(server, data.map.pseudo_frames, g, "/map/pseudo_frames")
    if pseudo is not None:
        h.add_layer(pseudo)
    if added is not None or pseudo is not None:
        legend += [("points added by the update", palette.PSEUDO_POINTS),
                   ("pseudo-labelled frame", palette.PSEUDO_FRAMES)]

    for i, t in enumerate(data.trajectories):
        nodes = layers.add_trajectory(server, t, f"{i:02d}", g)
        h.trajectories.append(nodes)
        h.add_layer(nodes.plain)
    if data.trajectories:
        legend += [("ground truth", palette.GROUND_TRUTH), ("estimate", palette.ESTIMATE)]

    for i, r in enumerate(data.evaluations):
        layer = layers.add_evaluation(server, r, f"{i:02d}", g, on_query_click)
        if i > 0:  # one report's queries at a time, the others a toggle away
            layer.set_visible(False)
        h.add_layer(layer)
    if data.evaluations:
        legend += [("query not localized (at its ground truth)", palette.FAILURE)]

    for i, r in enumerate(data.slams):
        events, edges = layers.add_slam(server, r, f"{i:02d}", g)
        for layer in (events, edges):
            if layer.nodes:
                h.add_layer(layer)
        kinds = sorted({(e.type, e.accepted) for e in r.events})
        legend += [(f"{k.replace('_', ' ')} ({'accepted' if ok else 'rejected'})",
                    palette.EVENT_COLORS.get(k, palette.EVENT_COLORS["other"])[0 if ok else 1])
                   for k, ok in kinds]
        edge_kinds = sorted({(e.type, e.accepted) for e in r.edges})
        legend += [(f"graph edge: {k.replace('_', ' ')}" + ("" if ok else " (rejected)"),
                    palette.EDGE_COLORS.get(k, palette.OTHER_EDGE) if ok
                    else palette.REJECTED_EDGE) for k, ok in edge_kinds]

    for i, r in enumerate(data.pseudo_labels):
        layer = layers.add_pseudo_frames(server, r.frames, g, f"/pseudo_label/{i:02d}/frames")
        if layer is not None:
            layer.name = f"pseudo-labelled frames: {r.path.name}"
            h.add_layer(layer)

    marker = server.scene.add_camera_frustum(
        "/current_frame", fov=g.fov, aspect=g.aspect, scale=g.frustum_scale * 1.3,
        color=palette.CURRENT_FRAME, visible=False, cast_shadow=False, receive_shadow=False)
    current = h.add_layer(layers.Layer("current frame", [marker]))
    sources = _sources(data)
    if sources:
        h.playback = gui.Playback(server, g, sources, marker=marker, marker_layer=current)
        h.controls.update(gui.add_playback(server, h.playback))
    h.selection = gui.add_selection(server)
    h.controls.update(gui.add_layer_toggles(server, list(h.layers.values()), h.trajectories,
                                            point_nodes))
    with_errors = any(t.errors_m is not None for t in data.trajectories) or bool(
        data.evaluations)
    gui.add_legend(server, legend, with_errors)
    h.report_panels = gui.add_reports_panel(server, data.reports())
    return h
