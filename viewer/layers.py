"""Scene layers: map points, training cameras, trajectories, evaluate / slam / pseudo-label reports.

Each `add_*` function puts one layer's nodes on the server and returns them; many small things
(query cameras, graph edges, wireframes beyond the image budget) are batched into one node."""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass, field

import numpy as np

from slamreloc.geometry import Rigid3
from slamreloc.viewer import colors as palette
from slamreloc.viewer.camera_images import image_quads, quads_glb
from slamreloc.viewer.data import EvalReport, MapView, SlamReport, Trajectory


@dataclass
class Layer:
    """A named, toggleable set of scene nodes."""

    name: str
    nodes: list = field(default_factory=list)
    visible: bool = True

    def set_visible(self, visible: bool) -> None:
        self.visible = visible
        for node in self.nodes:
            node.visible = visible


@dataclass
class Geometry:
    """Scale of the scene, derived from the map: frustum size, point size, centre, up."""

    center: np.ndarray
    extent: float  # robust diagonal of the map, metres
    up: np.ndarray
    frustum_scale: float
    point_size: float
    fx: float = 500.0
    fy: float = 500.0
    width: int = 640
    height: int = 480

    @property
    def fov(self) -> float:
        return float(2 * np.arctan2(self.height / 2, self.fy))

    @property
    def aspect(self) -> float:
        return self.width / self.height


def scene_geometry(scene_map: MapView, up: np.ndarray) -> Geometry:
    pts = scene_map.points
    cams = np.array([f.world_from_cam.translation for f in scene_map.frames
                     if f.world_from_cam is not None]).reshape(-1, 3)
    ref = pts if len(pts) >= 10 else (cams if len(cams) else np.zeros((1, 3)))
    lo, hi = np.percentile(ref, 5, axis=0), np.percentile(ref, 95, axis=0)
    extent = float(max(np.linalg.norm(hi - lo), 0.1))
    center = np.median(ref, axis=0)
    cam = scene_map.camera
    g = Geometry(center, extent, up, frustum_scale=0.02 * extent, point_size=extent / 400)
    if cam is not None:
        g.fx, g.fy, g.width, g.height = cam.fx, cam.fy, cam.width, cam.height
    return g


def wxyz(pose: Rigid3) -> np.ndarray:
    x, y, z, w = pose.quat_xyzw()
    return np.array([w, x, y, z])


def frustum_segments(poses: list[Rigid3], g: Geometry, scale: float) -> np.ndarray:
    """(N*8, 2, 3) wireframe segments of camera frustums (apex to corners, image rectangle)."""
    if not poses:
        return np.zeros((0, 2, 3), np.float32)
    hw, hh = g.width / 2 / g.fx * scale, g.height / 2 / g.fy * scale
    corners = np.array([[-hw, -hh, scale], [hw, -hh, scale], [hw, hh, scale], [-hw, hh, scale]])
    rot = np.stack([p.rotation for p in poses])  # (N, 3, 3)
    t = np.stack([p.translation for p in poses])  # (N, 3)
    world = np.einsum("nij,kj->nki", rot, corners) + t[:, None]  # (N, 4, 3)
    apex = np.repeat(t[:, None], 4, axis=1)
    spokes = np.stack([apex, world], axis=2)  # (N, 4, 2, 3)
    rim = np.stack([world, np.roll(world, -1, axis=1)], axis=2)
    return np.concatenate([spokes, rim], axis=1).reshape(-1, 2, 3).astype(np.float32)


def cross_segments(centers: np.ndarray, size: float) -> np.ndarray:
    """(N*3, 2, 3): a 3D cross marking each centre."""
    offs = np.eye(3) * size
    segs = np.stack([centers[:, None] - offs, centers[:, None] + offs], axis=2)
    return segs.reshape(-1, 2, 3).astype(np.float32)


def polyline_segments(points: np.ndarray) -> np.ndarray:
    return np.stack([points[:-1], points[1:]], axis=1).astype(np.float32)




def point_shape(n_points: int) -> str:
    """Round points for small maps; squares beyond 100 k (no per-fragment discard: several
    times faster where WebGL runs in software)."""
    return "rounded" if n_points <= 100_000 else "square"


def _precision(points: np.ndarray) -> str:
    return "float32" if len(points) and np.abs(points).max() > 30 else "float16"


# ---------------------------------------------------------------- map
def add_map_points(server, scene_map: MapView, g: Geometry) -> tuple[Layer, Layer | None]:
    pts, cols = scene_map.points, scene_map.colors
    pseudo = scene_map.pseudo if scene_map.pseudo is not None else np.zeros(len(pts), bool)
    main = Layer("map points", [server.scene.add_point_cloud(
        "/map/points", pts[~pseudo], cols[~pseudo], point_size=g.point_size,
        point_shape=point_shape(len(pts)), precision=_precision(pts))])
    added = None
    if pseudo.any():
        n = int(pseudo.sum())
        added = Layer("points added by the update", [server.scene.add_point_cloud(
            "/map/pseudo_points", pts[pseudo], np.tile(np.uint8(palette.PSEUDO_POINTS), (n, 1)),
            point_size=g.point_size * 1.5, point_shape=point_shape(len(pts)),
            precision=_precision(pts))])
    return main, added


def add_training_cameras(server, scene_map: MapView, g: Geometry, on_click) -> Layer:
    """All training cameras as one wireframe node; the thumbnails (up to the image budget) as
    one textured node on their frustums' image rectangles, clickable (`camera_images`)."""
    layer = Layer("training cameras")
    posed = [f for f in scene_map.frames if f.world_from_cam is not None]
    if posed:
        segs = frustum_segments([f.world_from_cam for f in posed], g, g.frustum_scale)
        layer.nodes.append(server.scene.add_line_segments(
            "/map/cameras_wireframe", segs, palette.TRAINING_CAMERA, thickness=1.0,
            thickness_units="screen"))
    shown = [f for f in posed if f.thumbnail is not None]
    if shown:
        quads = image_quads([f.world_from_cam for f in shown], [f.thumbnail for f in shown],
                            g.fx, g.fy, g.width, g.height, g.frustum_scale)
        node = server.scene.add_glb("/map/camera_images", quads_glb(quads),
                                    cast_shadow=False, receive_shadow=False)

        def clicked(event) -> None:
            k = quads.pick(np.asarray(event.ray_origin), np.asarray(event.ray_direction))
            if k is not None:
                on_click(shown[k], event)

        node.on_click(clicked)
        layer.nodes.append(node)
    return layer


def add_pseudo_frames(server, frames, g: Geometry, name: str) -> Layer | None:
    poses = [f.world_from_cam for f in frames if f.world_from_cam is not None]
    if not poses:
        return None
    return Layer("pseudo-labelled frames", [server.scene.add_line_segments(
        name, frustum_segments(poses, g, g.frustum_scale), palette.PSEUDO_FRAMES,
        thickness=1.5, thickness_units="screen")])


# ---------------------------------------------------------------- trajectories
@dataclass
class TrajectoryNodes:
    plain: Layer  # green (ground truth) or red (estimate)
    by_error: object | None = None  # line node coloured by error, shown instead of `plain`


def add_trajectory(server, traj: Trajectory, key: str, g: Geometry) -> TrajectoryNodes:
    pos = traj.positions
    color = palette.GROUND_TRUTH if traj.kind == "groundtruth" else palette.ESTIMATE
    base = f"/trajectories/{key}"
    if len(pos) == 0:  # a session that never anchored writes one: a layer with nothing to show
        return TrajectoryNodes(Layer(f"{traj.kind}: {traj.name} (no poses)", []))
    if len(pos) >= 2:
        plain = server.scene.add_line_segments(f"{base}/line", polyline_segments(pos), color,
                                               thickness=2.5, thickness_units="screen")
    else:
        plain = server.scene.add_point_cloud(f"{base}/line", pos.astype(np.float32),
                                             np.uint8([color]), point_size=g.point_size * 4)
    nodes = TrajectoryNodes(Layer(f"{traj.kind}: {traj.name}", [plain]))
    errors = traj.errors_m
    if traj.kind == "estimate" and errors is not None and len(pos) >= 2:
        seg_err = np.fmax(errors[:-1], errors[1:])  # a segment shows its worse end
        cols = palette.error_colors(seg_err)
        nodes.by_error = server.scene.add_line_segments(
            f"{base}/by_error", polyline_segments(pos), cols[:, None].repeat(2, axis=1),
            thickness=3.0, thickness_units="screen", visible=False)
        nodes.plain.nodes.append(nodes.by_error)
    return nodes


# ---------------------------------------------------------------- evaluate report
def add_evaluation(server, report: EvalReport, key: str, g: Geometry, on_pick) -> Layer:
    """Each query's estimated camera coloured by its error; failures as a magenta frustum and
    cross where the ground truth is; a grey link from truth to estimate."""
    base = f"/evaluate/{key}"
    layer = Layer(f"queries: {report.path.name}")
    placed = [q for q in report.queries if q.estimate is not None]
    if placed:
        errs = np.array([q.translation_error_m if q.translation_error_m is not None else np.nan
                         for q in placed])
        cols = np.repeat(palette.error_colors(errs), 8, axis=0)
        layer.nodes.append(server.scene.add_line_segments(
            f"{base}/estimates", frustum_segments([q.estimate for q in placed], g,
                                                  g.frustum_scale * 0.8),
            cols[:, None].repeat(2, axis=1), thickness=2.0, thickness_units="screen"))
        pick = server.scene.add_batched_axes(
            f"{base}/pick", np.stack([wxyz(q.estimate) for q in placed]),
            np.stack([q.estimate.translation for q in placed]),
            axes_length=g.frustum_scale * 0.3, axes_radius=g.frustum_scale * 0.03)
        pick.on_click(lambda event: on_pick(placed[event.instance_index], event)
                      if event.instance_index is not None else None)
        layer.nodes.append(pick)
        linked = [q for q in placed if q.truth is not None]
        if linked:
            segs = np.stack([[q.truth.translation, q.estimate.translation] for q in linked])
            layer.nodes.append(server.scene.add_line_segments(
                f"{base}/links", segs.astype(np.float32), palette.ERROR_LINK, thickness=1.0,
                thickness_units="screen"))
    failed = [q for q in report.queries if q.failed and q.truth is not None]
    if failed:
        truths = [q.truth for q in failed]
        segs = np.concatenate([frustum_segments(truths, g, g.frustum_scale * 0.8),
                               cross_segments(np.stack([t.translation for t in truths]),
                                              g.frustum_scale * 0.5)])
        layer.nodes.append(server.scene.add_line_segments(
            f"{base}/failures", segs, palette.FAILURE, thickness=3.0, thickness_units="screen"))
    return layer


# ---------------------------------------------------------------- slam report
def add_slam(server, report: SlamReport, key: str, g: Geometry) -> tuple[Layer, Layer]:
    """Events as coloured markers (accepted / rejected in distinct colours) with labels for
    kidnappings and recoveries; pose-graph edges as lines, one node per type and status."""
    base = f"/slam/{key}"
    events = Layer(f"slam events: {report.path.name}")
    groups = defaultdict(list)
    for e in report.events:
        if e.position is not None:
            groups[(e.type, e.accepted)].append(e.position)
    for (kind, ok), pos in sorted(groups.items()):
        color = palette.EVENT_COLORS.get(kind, palette.EVENT_COLORS["other"])[0 if ok else 1]
        pts = np.asarray(pos, np.float32)
        events.nodes.append(server.scene.add_point_cloud(
            f"{base}/events/{kind}_{'accepted' if ok else 'rejected'}", pts,
            np.tile(np.uint8(color), (len(pts), 1)), point_size=g.point_size * 8,
            point_shape="circle", precision=_precision(pts)))
    labelled = [e for e in report.events if e.type in ("kidnap", "recovery")
                and e.position is not None][:60]
    for i, e in enumerate(labelled):
        text = f"{e.type} @ {e.frame}" if e.frame is not None else e.type
        events.nodes.append(server.scene.add_label(
            f"{base}/labels/{i:03d}", text, position=e.position + g.up * g.frustum_scale,
            font_screen_scale=0.7))
    edges = Layer(f"pose graph: {report.path.name}")
    by_type = defaultdict(list)
    for e in report.edges:
        by_type[(e.type, e.accepted)].append((e.a, e.b))
    for (kind, ok), segs in sorted(by_type.items()):
        color = palette.EDGE_COLORS.get(kind, palette.OTHER_EDGE) if ok else palette.REJECTED_EDGE
        edges.nodes.append(server.scene.add_line_segments(
            f"{base}/edges/{kind}_{'accepted' if ok else 'rejected'}",
            np.asarray(segs, np.float32), color, thickness=1.5 if kind == "odometry" else 2.5,
            thickness_units="screen"))
    return events, edges
