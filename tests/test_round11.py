"""Issue 43, the eleventh attack round's CLI findings as regression tests: a trajectory's
names sidecar shared with another trajectory (G2), outputs that replaced a COLMAP model or a
JSON file slamreloc did not write (G3), a full disk between two outputs of one command (G4)."""

from __future__ import annotations

import errno
import json
import shutil
from pathlib import Path

import pytest

from slamreloc.cli import jobs
from slamreloc.datasets.poses import read_own_trajectory
from tests.fuzzing import run_cli
from tests.test_cli_round5 import one_line_exit_2
from tests.test_fuzz_inputs import _tiny_map
from tests.test_round10 import _edited


@pytest.fixture(scope="module")
def tiny_map(tmp_path_factory) -> Path:
    return _tiny_map(tmp_path_factory.mktemp("round11") / "map")


def _bytes(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir()) if p.is_file()}


# ---- G2: every X.* trajectory shares X.names.txt ---------------------------------------------
@pytest.mark.parametrize("other_name, out_name", [("t.txt", "t.csv"), ("t.csv", "t.txt"),
                                                  ("t.txt", "t.foo"), ("t", "t.txt")])
def test_a_names_sidecar_of_another_trajectory_is_never_replaced(tiny_map, tmp_path,
                                                                  other_name, out_name):
    code, err = run_cli(["export", str(tiny_map), "--tum", str(tmp_path / other_name)])
    assert code == 0, err
    read_own_trajectory(tmp_path / other_name)
    before = _bytes(tmp_path)
    one_line_exit_2(["export", str(tiny_map), "--tum", str(tmp_path / out_name)],
                    f"also names the stamps of the trajectory {tmp_path / other_name}")
    assert _bytes(tmp_path) == before


def test_an_inputs_names_sidecar_is_not_an_output(small_map, scene_dir, tmp_path):
    """`slam --poses gt.txt --trajectory gt.foo`: gt.foo's sidecar is the input's."""
    code, err = run_cli(["export", str(small_map.root), "--tum", str(tmp_path / "gt.txt")])
    assert code == 0, err
    before = _bytes(tmp_path)
    one_line_exit_2(["slam", str(scene_dir), "--map", str(small_map.root), "--split", "query",
                     "--poses", str(tmp_path / "gt.txt"), "--trajectory",
                     str(tmp_path / "gt.foo"), "--report", str(tmp_path / "s.json")],
                    "--trajectory", "gt.names.txt")
    assert _bytes(tmp_path) == before


def test_a_trajectory_of_its_own_name_is_replaced(tiny_map, tmp_path):
    for _ in range(2):
        code, err = run_cli(["export", str(tiny_map), "--tum", str(tmp_path / "t.txt")])
        assert code == 0, err
    assert sorted(_bytes(tmp_path)) == ["t.names.txt", "t.txt"]


# ---- G3b: a JSON file with one report key is not a report --------------------------------------
def test_a_json_with_some_of_a_reports_fields_is_not_replaced(small_map, scene_dir, tmp_path):
    notes = tmp_path / "n.json"
    notes.write_text(json.dumps({"n_queries": 3, "note": "my own notes"}))
    one_line_exit_2(["evaluate", str(small_map.root), str(scene_dir), "--split", "query",
                     "--method", "matching", "--report", str(notes)],
                    "--report", "not a slamreloc report")
    assert json.loads(notes.read_text()) == {"n_queries": 3, "note": "my own notes"}
    code, err = run_cli(["evaluate", str(small_map.root), str(scene_dir), "--split", "query",
                         "--method", "matching", "--report", str(tmp_path / "r.json")])
    assert code == 0, err
    code, err = run_cli(["evaluate", str(small_map.root), str(scene_dir), "--split", "query",
                         "--method", "matching", "--report", str(tmp_path / "r.json")])
    assert code == 0, err  # its own report is replaced


# ---- G4: outputs of one command are all new or all old, a full disk included ----------------
def test_a_full_disk_at_the_report_leaves_the_trajectory_as_it_was(small_map, scene_dir,
                                                                   tmp_path, monkeypatch):
    argv = ["evaluate", str(small_map.root), str(scene_dir), "--split", "query", "--method",
            "matching", "--report", str(tmp_path / "r.json"),
            "--trajectory", str(tmp_path / "t.txt")]
    code, err = run_cli([*argv[:4], "map", *argv[5:]])  # an earlier run, of the other split
    assert code == 0, err
    before = _bytes(tmp_path)
    assert sorted(before) == ["r.json", "t.names.txt", "t.txt"]

    def full(path, data):
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    monkeypatch.setattr(jobs, "write_json", full)
    code, err = run_cli(argv)
    assert code == 2 and "No space left" in err and "r.json" in err, err
    assert _bytes(tmp_path) == before  # no temporary left, nothing replaced


def test_a_trajectory_and_its_names_are_written_together(tiny_map, tmp_path, monkeypatch):
    from slamreloc import geometry

    code, err = run_cli(["export", str(tiny_map), "--tum", str(tmp_path / "t.txt")])
    assert code == 0, err
    shutil.copy(tmp_path / "t.txt", tmp_path / "keep.txt")
    (tmp_path / "t.txt").write_text((tmp_path / "t.txt").read_text().replace("0.0", "0.1", 1))
    before = _bytes(tmp_path)
    blocker = tmp_path / "blocker"
    blocker.write_text("a file, so no folder can be made under it\n")
    before["blocker"] = blocker.read_bytes()
    monkeypatch.setattr(geometry, "names_sidecar", lambda path: blocker / "t.names.txt")
    with pytest.raises(OSError):
        geometry.write_tum_trajectory(tmp_path / "t.txt", [0.0], [geometry.Rigid3.identity()],
                                      names=["a"])
    assert _bytes(tmp_path) == before


# ---- G7: a map's record follows the report rules by field name, and agrees with its files ----
def _set(section: str, key: str, value):
    return lambda doc: doc.setdefault(section, {}).__setitem__(key, value)


@pytest.mark.parametrize("edit, message", [
    (_set("train", "cpu_s", -1), "train.cpu_s is a measure (distance, angle or time), a number "
                                 ">= 0; got -1"),
    (_set("timings_s", "train_s", -1), "timings_s.train_s is a measure"),
    (_set("labels", "labelled_fraction", 2.0), "'labels.labelled_fraction' must be a fraction"),
    (_set("train", "resumed_at_epoch", 999), "'train.resumed_at_epoch' must be a whole number "
                                             "of epochs in 0..0"),
    (_set("train", "averaged_epochs", -1), "'train.averaged_epochs' must be a whole number"),
    (_set("dataset", "metric", "yes"), "'dataset.metric' must be true or false, got 'yes'"),
    (_set("labels", "median_reproj_error_deg", 400.0), "labels.median_reproj_error_deg is an "
                                                       "angle"),
])
def test_map_records_follow_one_rule_per_value_kind(tiny_map, tmp_path, edit, message):
    from slamreloc.map.format import META

    out = _edited(tiny_map, tmp_path / "m", edit)
    line = one_line_exit_2(["export", str(out), "--tum", str(tmp_path / "t.txt")],
                           str(out / META), message)
    assert not (tmp_path / "t.txt").exists(), line


def test_a_surface_of_another_size_than_recorded_is_refused(small_map, tmp_path):
    from slamreloc.errors import InputError
    from slamreloc.map.scene_map import SceneMap

    assert small_map.surface is not None
    n = len(small_map.surface.points)
    SceneMap.load(_edited(small_map.root, tmp_path / "same", _set("surface", "n_points", n))
                  ).surface  # noqa: B018 - the recorded count is the file's
    out = _edited(small_map.root, tmp_path / "m", _set("surface", "n_points", 5))
    with pytest.raises(InputError, match=f"holds {n} points, but .* says 'surface.n_points' 5"):
        SceneMap.load(out).surface  # noqa: B018


# ---- G8: an evaluate report's `map.parameters` is a count ------------------------------------
def test_a_reports_parameter_count_is_a_count(tmp_path):
    from slamreloc.errors import InputError
    from slamreloc.viewer.reports import read_json

    path = tmp_path / "r.json"
    path.write_text(json.dumps({"n_queries": 0, "per_query": [], "map": {"parameters": -3}}))
    with pytest.raises(InputError, match="map.parameters is a count, a whole number >= 0"):
        read_json(path)


# ---- minor: a folder output's temporary path in the way is refused before the work ----------
def test_a_map_writers_temporary_folder_in_the_way_is_refused_at_once(scene_dir, tmp_path):
    import os

    mine = tmp_path / f".m.tmp-{os.getpid()}"
    mine.mkdir()
    (mine / "notes.txt").write_text("a user's\n")
    one_line_exit_2(["map", str(scene_dir), "--out", str(tmp_path / "m"), "--arch", "tiny",
                     "--epochs", "1"], "its temporary path", "not made by this process")
    assert (mine / "notes.txt").read_text() == "a user's\n" and not (tmp_path / "m").exists()
