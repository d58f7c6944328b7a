"""Attack round 35, outputs: every position a slam report gives the viewer (an event's, a graph
edge's ends) keeps one coordinate bound; `localize` names two images of one file name by their
paths, so that its lines read back as a pose file of distinct names."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from slamreloc.errors import InputError
from slamreloc.viewer import ViewerInputs, load_scene_data
from tests.fuzzing import run_cli_output


def _slam_report(folder: Path, edge: dict) -> Path:
    path = folder / "R.json"
    path.write_text(json.dumps({
        "n_frames": 3, "events": [{"frame": 0, "type": "kidnap", "position": [1, 2, 3]}],
        "graph_edges": [{"type": "odometry", "a": [0, 0, 0], "b": [1, 0, 0]}, edge]}))
    return path


# ---- T7: a graph edge's ends lie within the bound an event's position keeps ------------------
@pytest.mark.parametrize("edge, field", [
    ({"type": "odometry", "a": [1e300, 0, 0], "b": [0, 0, 0]}, "graph_edges[1].a"),
    ({"type": "loop_closure", "a": [0, 0, 0], "b": [0, -2e9, 0]}, "graph_edges[1].b"),
    ({"type": "odometry", "from_position": [0, 0, 1.5e9], "to_position": [0, 0, 0]},
     "graph_edges[1].from_position"),
    ({"type": "odometry", "from_position": [0, 0, 0], "to_position": [0, 0, -1e10]},
     "graph_edges[1].to_position"),
])
def test_graph_edge_ends_beyond_the_bound_are_refused(small_map, tmp_path, edge, field):
    report = _slam_report(tmp_path, edge)
    message = f"{report}: {field} lies beyond 1e+09 m"
    with pytest.raises(InputError) as err:
        load_scene_data(ViewerInputs(small_map.root, reports=[report]))
    assert str(err.value) == message
    code, out, err_text = run_cli_output(["view", str(small_map.root), "--report", str(report),
                                          "--port", "0"], hang_s=120)
    assert code == 2 and err_text.strip().splitlines() == [f"error: {message}"], err_text


def test_graph_edge_ends_within_the_bound_are_read(small_map, tmp_path):
    report = _slam_report(tmp_path, {"type": "odometry", "a": [1e9, 0, 0], "b": [0, 0, -1e9]})
    data = load_scene_data(ViewerInputs(small_map.root, reports=[report]))
    (slam,) = data.slams
    assert [e.a[0] for e in slam.edges] == [0.0, 1e9] and slam.edges[1].b[2] == -1e9


# ---- T8: two images of one file name are named by their paths ---------------------------------
def test_localize_names_images_of_one_file_name_by_their_paths(small_map, scene_dir, tmp_path,
                                                              monkeypatch):
    frame = scene_dir / "seq-02" / "frame-000000.color.png"
    for folder in ("a", "b b"):
        (tmp_path / "imgs" / folder).mkdir(parents=True)
        shutil.copy(frame, tmp_path / "imgs" / folder / "q.png")
    shutil.copy(frame, tmp_path / "imgs" / "other.png")
    monkeypatch.chdir(tmp_path)
    code, out, err = run_cli_output(["localize", str(small_map.root), "imgs/a/q.png",
                                     "imgs/b b/q.png", "imgs/other.png", "imgs/a/q.png"],
                                    hang_s=300)
    assert code == 0, err
    names = [line.split()[0] for line in out.splitlines()]
    # the same image given twice by the same path is the same image: one name twice
    assert names == ["imgs/a/q.png", "imgs/b%20b/q.png", "other.png", "imgs/a/q.png"], out
    assert all(len(line.split()) == 9 for line in out.splitlines()), out


def test_localize_names_a_lone_image_by_its_file_name(small_map, scene_dir, tmp_path,
                                                     monkeypatch):
    frame = scene_dir / "seq-02" / "frame-000000.color.png"
    (tmp_path / "imgs" / "a").mkdir(parents=True)
    shutil.copy(frame, tmp_path / "imgs" / "a" / "q.png")
    monkeypatch.chdir(tmp_path)
    code, out, err = run_cli_output(["localize", str(small_map.root), "imgs/a/q.png",
                                     "imgs/a/q.png"], hang_s=300)
    assert code == 0, err
    assert [line.split()[0] for line in out.splitlines()] == ["q.png", "q.png"], out
