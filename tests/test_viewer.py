"""The viewer's scene, checked on the server side (no browser): node names, point counts and
colours of the layers, the controls, and bad input."""

from __future__ import annotations

import json
import shutil
import socket
import subprocess
import sys
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest

from slamreloc.errors import InputError
from slamreloc.map.format import LABELLED, NEW
from slamreloc.map.scene_map import SceneMap
from slamreloc.viewer import ViewerInputs, build_scene, load_scene_data, make_server
from slamreloc.viewer import colors as palette
from slamreloc.viewer.gui import report_table
from slamreloc.viewer.map_view import voxel_downsample
from slamreloc.viewer.trajectories import read_trajectory
from tests.viewer_support import BIG_ERROR, FAILED, pseudo_label_map

ROOT = Path(__file__).resolve().parents[1]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextmanager
def scene(inputs: ViewerInputs):
    server = make_server("127.0.0.1", free_port())
    try:
        handles = build_scene(server, load_scene_data(inputs))
        yield server, handles
    finally:
        if "handles" in locals():
            handles.stop()
        server.stop()


def nodes(server) -> dict:
    return dict(server.scene._handle_from_node_name)


def full_inputs(case, **kw) -> ViewerInputs:
    return ViewerInputs(case.map_dir, [case.trajectory], [case.report, case.slam_report], **kw)


def test_map_points_take_the_image_colour_at_their_keypoint(viewer_case):
    with scene(ViewerInputs(viewer_case.map_dir)) as (server, h):
        points = nodes(server)["/map/points"]
        assert points.points.shape == (viewer_case.n_points, 3)
        assert h.data.map.color_source == "image"
        np.testing.assert_array_equal(points.colors, viewer_case.truth_colors)


def test_map_points_coloured_by_height_without_images(viewer_case, tmp_path):
    moved = tmp_path / "map"
    shutil.copytree(viewer_case.map_dir, moved)
    meta = json.loads((moved / "slamreloc_map.json").read_text())
    meta["dataset"]["root"] = str(tmp_path / "gone")
    (moved / "slamreloc_map.json").write_text(json.dumps(meta))
    with scene(ViewerInputs(moved)) as (server, h):
        pts = nodes(server)["/map/points"]
        assert h.data.map.color_source == "height"
        height = pts.points.astype(float) @ h.geometry.up
        low, high = height < np.percentile(height, 10), height > np.percentile(height, 90)
        # low points take the ramp's dark purple end, high ones its yellow end
        assert pts.colors[low].mean(axis=0)[1] < 80 < pts.colors[high].mean(axis=0)[1]
    # ... and --dataset brings the images back
    with scene(ViewerInputs(moved, dataset=viewer_case.scene)) as (server, h):
        np.testing.assert_array_equal(nodes(server)["/map/points"].colors,
                                      viewer_case.truth_colors)


def test_large_maps_are_voxel_downsampled(viewer_case):
    rng = np.random.default_rng(0)
    pts = rng.uniform(-2, 2, (200_000, 3)).astype(np.float32)
    keep, voxel = voxel_downsample(pts, 20_000)
    assert 10_000 < len(keep) <= 20_000 and voxel > 0
    np.testing.assert_allclose(pts[keep].min(axis=0), -2, atol=0.1)  # still spans the volume
    np.testing.assert_allclose(pts[keep].max(axis=0), 2, atol=0.1)
    assert len(voxel_downsample(pts, 300_000)[0]) == 200_000
    with scene(ViewerInputs(viewer_case.map_dir, max_points=2000)) as (server, h):
        n = len(nodes(server)["/map/points"].points)
        assert n <= 2000 and h.data.map.n_points_total == viewer_case.n_points


def _glb_mesh(node):
    import io

    import trimesh

    scene = trimesh.load(io.BytesIO(node.glb_data), file_type="glb")
    return next(iter(scene.geometry.values()))


def test_training_cameras_are_one_wireframe_and_one_textured_node(viewer_case):
    with scene(ViewerInputs(viewer_case.map_dir)) as (server, h):
        n = nodes(server)
        assert not [k for k in n if k.startswith("/map/cameras/")]  # no node per camera
        wire = n["/map/cameras_wireframe"]
        assert wire.points.shape == (viewer_case.n_train * 8, 2, 3)
        mesh = _glb_mesh(n["/map/camera_images"])
        assert mesh.vertices.shape == (viewer_case.n_train * 4, 3)
        # each quad is its camera's image rectangle: the base of its wireframe frustum
        rim = wire.points.reshape(viewer_case.n_train, 8, 2, 3)[:, 4:, 0]
        np.testing.assert_allclose(mesh.vertices.reshape(-1, 4, 3), rim, atol=1e-4)
        texture = mesh.visual.material.baseColorTexture
        assert texture.format == "JPEG" and max(texture.size) <= 2048
    with scene(ViewerInputs(viewer_case.map_dir, max_images=10)) as (server, h):
        assert len(_glb_mesh(nodes(server)["/map/camera_images"]).vertices) == 10 * 4


def test_image_atlas_keeps_each_thumbnail_in_its_cell():
    from slamreloc.viewer.camera_images import build_atlas

    images = [np.full((120, 160, 3), 10 * i, np.uint8) for i in range(20)]
    atlas, cells = build_atlas(images, max_side=300)
    assert max(atlas.shape[:2]) <= 300
    for i, (x0, y0, x1, y1) in enumerate(cells):
        assert (atlas[y0:y1, x0:x1] == 10 * i).all()
        assert (x1 - x0) * 120 == pytest.approx((y1 - y0) * 160, rel=0.05)


def test_clicking_a_camera_image_shows_its_image_and_name(viewer_case):
    with scene(ViewerInputs(viewer_case.map_dir)) as (server, h):
        node = nodes(server)["/map/camera_images"]
        before = h.selection.image.image.copy()
        pose = h.data.map.frames[7].world_from_cam
        axis = pose.rotation[:, 2]
        for origin, direction in ((pose.translation + 0.5 * h.geometry.frustum_scale * axis,
                                   axis),  # the ray through the middle of frame 7's image
                                  (h.geometry.center + 100 * h.geometry.up,
                                   h.geometry.up)):  # a ray away from the scene: no change
            event = type("Event", (), {"client": None, "ray_origin": tuple(origin),
                                       "ray_direction": tuple(direction)})()
            for entry in node._impl.click_cb:
                entry.callback(event)
            assert h.data.map.frames[7].name in h.selection.text.content
        assert h.selection.image.visible and h.selection.image.image.shape != before.shape


def test_trajectories_green_truth_red_estimate_and_error_colours(viewer_case):
    with scene(full_inputs(viewer_case)) as (server, h):
        n = nodes(server)
        est, gt = n["/trajectories/00/line"], n["/trajectories/01/line"]
        n_est = int(np.isfinite(viewer_case.estimate_error_m).sum())
        assert est.points.shape == (n_est - 1, 2, 3) and gt.points.shape == (n_est - 1, 2, 3)
        assert tuple(est.colors.reshape(-1, 3)[0]) == palette.ESTIMATE
        assert tuple(gt.colors.reshape(-1, 3)[0]) == palette.GROUND_TRUTH
        traj = h.data.trajectories[0]
        ok = np.isfinite(viewer_case.estimate_error_m)
        np.testing.assert_allclose(traj.errors_m, viewer_case.estimate_error_m[ok], atol=1e-4)
        by_err = n["/trajectories/00/by_error"]
        assert not by_err.visible
        seg = by_err.colors[:, 0].astype(int)  # segment colours: the 30 cm frame is red
        big = list(np.flatnonzero(ok)).index(BIG_ERROR)
        assert seg[big - 1][0] > 200 and seg[big - 1][1] < 80
        assert seg[0][1] > seg[0][0]  # a 1-3 cm segment is green-ish
        h.controls["error_colours"].value = True
        assert by_err.visible and not est.visible
        h.controls[f"layer:{h.trajectories[0].plain.name}"].value = False
        assert not by_err.visible and not est.visible


def test_evaluation_queries_coloured_by_error_and_failures_at_ground_truth(viewer_case):
    with scene(full_inputs(viewer_case)) as (server, h):
        n = nodes(server)
        n_ok = int(np.isfinite(viewer_case.estimate_error_m).sum())
        est = n["/evaluate/00/estimates"]
        assert est.points.shape == (n_ok * 8, 2, 3)
        colours = est.colors[::8, 0]
        ok = np.isfinite(viewer_case.estimate_error_m)
        expected = palette.error_colors(viewer_case.estimate_error_m[ok])
        np.testing.assert_array_equal(colours, expected)
        fail = n["/evaluate/00/failures"]
        assert fail.points.shape == (len(FAILED) * (8 + 3), 2, 3)
        assert tuple(fail.colors.reshape(-1, 3)[0]) == palette.FAILURE
        truth = h.data.evaluations[0].queries[FAILED[0]].truth.translation
        np.testing.assert_allclose(fail.points[0, 0], truth, atol=1e-3)  # frustum apex
        assert len(n["/evaluate/00/pick"].batched_positions) == n_ok


def test_slam_events_and_graph_edges_by_type_and_status(viewer_case):
    with scene(full_inputs(viewer_case)) as (server, h):
        n = nodes(server)
        names = {k for k in n if k.startswith("/slam/00/")}
        for expected in ("events/kidnap_accepted", "events/recovery_accepted",
                         "events/loop_closure_accepted", "events/loop_closure_rejected",
                         "events/relocalization_rejected", "events/tracking_lost_accepted",
                         "edges/odometry_accepted", "edges/loop_closure_accepted",
                         "edges/loop_closure_rejected"):
            assert f"/slam/00/{expected}" in names, expected
        assert not any("keyframe" in k for k in names)
        ok, bad = n["/slam/00/events/loop_closure_accepted"], n[
            "/slam/00/events/loop_closure_rejected"]
        assert tuple(ok.colors[0]) != tuple(bad.colors[0])
        assert len(n["/slam/00/edges/odometry_accepted"].points) == 10
        assert tuple(n["/slam/00/edges/loop_closure_rejected"].colors.reshape(-1, 3)[0]) == \
            palette.REJECTED_EDGE
        # the kidnap sits on the estimated trajectory at frame 6 (stamp 6 of the TUM file)
        traj = read_trajectory(viewer_case.trajectory)
        k = list(traj.stamps).index(6.0)
        np.testing.assert_allclose(n["/slam/00/events/kidnap_accepted"].points[0],
                                   traj.poses[k].translation, atol=2e-3)
        labels = [v.text for key, v in n.items() if key.startswith("/slam/00/labels/")]
        assert any(t.startswith("kidnap") for t in labels)
        assert any(t.startswith("recovery") for t in labels)


@pytest.fixture(scope="module")
def updated_map(small_map, scene_dir, tmp_path_factory):
    """The demo's `map_updated/` and `report_pseudo_label.json`, by the real pseudo-label."""
    new_map, report = pseudo_label_map(small_map.root, scene_dir,
                                       tmp_path_factory.mktemp("updated"))
    return new_map, report, json.loads(report.read_text())


def test_updated_map_shows_the_updates_frames_and_pseudo_labels(updated_map):
    """What the updater writes (provenance.npz, the report's poses) is what the viewer shows:
    every pseudo-labelled point flagged, every registered frame drawn."""
    new_map, report, rep = updated_map
    source = SceneMap.load(new_map, regressor=False).provenance.source
    n_flagged = int((source != LABELLED).sum())
    assert n_flagged == rep["n_database_after"] - rep["n_database_before"]
    assert n_flagged == rep["n_pseudo_labels"] > 0 and (source == NEW).any()
    assert rep["n_frames_registered"] == len(rep["poses"]) > 0
    data = load_scene_data(ViewerInputs(new_map, reports=[report], max_points=10 ** 9))
    assert data.map.voxel_size == 0 and int(data.map.pseudo.sum()) == n_flagged
    assert [f.name for f in data.map.pseudo_frames] == list(rep["poses"])
    for frame in data.map.pseudo_frames:
        np.testing.assert_allclose(frame.world_from_cam.matrix(), rep["poses"][frame.name],
                                   atol=1e-6)
    [shown] = data.pseudo_labels
    assert [f.name for f in shown.frames] == list(rep["poses"])
    with scene(ViewerInputs(new_map, reports=[report], max_points=10 ** 9)) as (server, h):
        n = nodes(server)
        added = n["/map/pseudo_points"]
        assert len(added.points) == n_flagged
        assert (added.colors == palette.PSEUDO_POINTS).all()
        assert len(n["/map/points"].points) == rep["n_database_before"]
        assert len(n["/map/pseudo_frames"].points) == 8 * rep["n_frames_registered"]
        assert len(n["/pseudo_label/00/frames"].points) == 8 * len(rep["poses"])
        assert "points added by the update" in h.layers


def test_a_map_never_updated_has_no_update_layers(viewer_case):
    with scene(ViewerInputs(viewer_case.map_dir)) as (server, h):
        assert h.data.map.pseudo is None and h.data.map.pseudo_frames == []
        assert not [k for k in nodes(server) if "pseudo" in k]


def test_frame_slider_moves_marker_image_and_text(viewer_case):
    with scene(full_inputs(viewer_case)) as (server, h):
        pb = h.playback
        assert pb.current.name.startswith("estimate")
        first = pb.image.image.copy()
        h.controls["slider"].value = 4
        traj = h.data.trajectories[0]
        np.testing.assert_allclose(pb.marker.position, traj.poses[4].translation, atol=1e-6)
        assert "30.0 cm" in pb.text.content  # frame 4 of the estimate is the 30 cm query
        assert not np.array_equal(pb.image.image, first)
        h.controls["next"]._impl.update_cb[0](None)
        assert h.controls["slider"].value == 5
        h.controls["source"].value = next(s.name for s in pb.sources
                                          if s.name.startswith("queries"))
        h.controls["slider"].value = FAILED[0]
        assert "not localized" in pb.text.content


def test_report_numbers_table(viewer_case):
    table = report_table(json.loads(viewer_case.report.read_text()))
    assert "| n_queries | 20 |" in table and "| recall.5cm5deg | 0.85 |" in table
    assert "| per_query | 20 entries |" in table
    with scene(full_inputs(viewer_case)) as (server, h):
        assert len(h.report_panels) == 2
        assert "ate_rmse_m" in h.report_panels[1].content


def test_server_binds_localhost_and_reports_the_port_it_got():
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        server = make_server("127.0.0.1", port)
        try:
            assert server.get_host() == "127.0.0.1"
            assert server.get_port() != port
        finally:
            server.stop()


def test_bad_input_is_one_line_error(viewer_case, tmp_path):
    with pytest.raises(InputError, match="trajectory file not found"):
        load_scene_data(ViewerInputs(viewer_case.map_dir, [tmp_path / "missing.txt"]))
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    with pytest.raises(InputError, match="bad.json: not valid JSON"):
        load_scene_data(ViewerInputs(viewer_case.map_dir, reports=[bad]))
    bad_traj = tmp_path / "bad.txt"
    bad_traj.write_text("0 1 2 3 0 0 0\n")
    with pytest.raises(InputError, match="expected 8 fields"):
        load_scene_data(ViewerInputs(viewer_case.map_dir, [bad_traj]))
    with pytest.raises(InputError, match="not a slamreloc map"):
        load_scene_data(ViewerInputs(tmp_path))
    run = subprocess.run([sys.executable, "-m", "slamreloc.cli", "view", str(viewer_case.map_dir),
                          "--report", str(bad)], capture_output=True, text=True, timeout=120,
                         cwd=ROOT)
    assert run.returncode == 2
    assert run.stderr.strip().splitlines() == [
        f"error: {bad}: not valid JSON (Expecting property name enclosed in double quotes: "
        "line 1 column 2 (char 1))"]


def test_inputs_that_are_not_files_or_folders_are_named(viewer_case, tmp_path):
    """A named pipe or a device given as a report, trajectory or dataset: one line saying
    what it is (not "not found"), exit 2, the pipe never opened for a blocking read."""
    import os

    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    png = tmp_path / "img.png"
    png.write_bytes(b"not read")
    for path, kind in ((fifo, "a named pipe"), (Path(os.devnull), "a device")):
        with pytest.raises(InputError, match=f"{path}: report is not a regular file \\({kind}"):
            load_scene_data(ViewerInputs(viewer_case.map_dir, reports=[path]))
        with pytest.raises(InputError,
                           match=f"{path}: trajectory is not a regular file \\({kind}"):
            load_scene_data(ViewerInputs(viewer_case.map_dir, [path]))
        with pytest.raises(InputError, match=f"{path}: dataset exists and is {kind}, not a "
                                             "folder"):
            load_scene_data(ViewerInputs(viewer_case.map_dir, dataset=path))
    with pytest.raises(InputError, match="img.png: dataset exists and is a file, not a folder"):
        load_scene_data(ViewerInputs(viewer_case.map_dir, dataset=png))
    with pytest.raises(InputError, match="nope: dataset folder not found"):
        load_scene_data(ViewerInputs(viewer_case.map_dir, dataset=tmp_path / "nope"))
    with pytest.raises(InputError, match="missing.json: report file not found"):
        load_scene_data(ViewerInputs(viewer_case.map_dir, reports=[tmp_path / "missing.json"]))
    for option in ("--report", "--trajectory", "--dataset"):
        run = subprocess.run([sys.executable, "-m", "slamreloc.cli", "view",
                              str(viewer_case.map_dir), "--port", "0", option, str(fifo)],
                             capture_output=True, text=True, timeout=120, cwd=ROOT)
        assert run.returncode == 2, (option, run.stderr)
        lines = run.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith(f"error: {fifo}: ") and \
            "a named pipe" in lines[0], (option, lines)


def test_trajectory_first_column_may_be_names(viewer_case, tmp_path):
    named = tmp_path / "named.txt"
    lines = viewer_case.trajectory.read_text().splitlines()
    names = dict(line.split(maxsplit=1) for line in
                 viewer_case.trajectory.with_suffix(".names.txt").read_text().splitlines())
    named.write_text("".join(f"{names[line.split()[0]]} {line.split(maxsplit=1)[1]}\n"
                             for line in lines))
    with scene(ViewerInputs(viewer_case.map_dir, [named])) as (server, h):
        traj = h.data.trajectories[0]
        assert traj.names[0] == viewer_case.query_names[0]
        ok = np.isfinite(viewer_case.estimate_error_m)
        np.testing.assert_allclose(traj.errors_m, viewer_case.estimate_error_m[ok], atol=1e-4)


def test_timestamps_shared_by_sequences_take_the_truth_of_the_matching_one(viewer_case,
                                                                          tmp_path):
    """A TUM file with the frames' own timestamps and no names (what other SLAM systems
    write): every synthetic sequence has the stamps 0, 1/30, ...; the ground truth must come
    from the sequence the poses belong to (seq-02), not the first one with those stamps."""
    from slamreloc.datasets import load_dataset

    queries = {q.name: q for q in load_dataset(viewer_case.scene).frames("test")}
    names = [line.split(maxsplit=1)[1] for line in
             viewer_case.trajectory.with_suffix(".names.txt").read_text().splitlines()]
    stamped = tmp_path / "stamped.txt"
    stamped.write_text("".join(
        f"{queries[n].timestamp:.6f} {line.split(maxsplit=1)[1]}\n"
        for n, line in zip(names, viewer_case.trajectory.read_text().splitlines())))
    with scene(ViewerInputs(viewer_case.map_dir, [stamped])) as (server, h):
        traj = h.data.trajectories[0]
        assert traj.names == names
        ok = np.isfinite(viewer_case.estimate_error_m)
        np.testing.assert_allclose(traj.errors_m, viewer_case.estimate_error_m[ok], atol=1e-4)
