"""Issue 43, what the thirteenth attack round left: a kill -9 among a command's renames (J3),
export's model swap that could not be undone, `--report -`, the recorded training device, and
the instant between a command's end and its exit."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from slamreloc.errors import InputError
from slamreloc.io.fileio import (commit_output, outputs_together, remove_dead_leftovers,
                                 write_json)

REPO = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"}
# the installed package (its wings mapped in: `slamreloc.pseudo_label`), run from elsewhere
INSTALLED = {k: v for k, v in ENV.items() if k != "PYTHONPATH"}


def _dead_pid() -> int:
    """The id of a process that has just ended (not given again in a test's time)."""
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def _tree(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*"))
            if p.is_file()}


# ---- J3: what a killed writer leaves beside a file output ----------------------------------
def test_a_killed_writers_temporaries_go_with_the_next_write(tmp_path):
    """A kill -9 leaves `.r.tmp-PID.json` (the new report not yet renamed in) and
    `.r.old-PID.json` (the second name of the report it replaced): the next writer of r.json
    removes them. A live writer's, a user's file of a like name, a folder and a link stay."""
    dead = _dead_pid()
    live = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        report = tmp_path / "r.json"
        report.write_text("{}")
        debris = [f".r.tmp-{dead}.json", f".r.old-{dead}.json"]
        kept = [f".r.tmp-{live.pid}.json", ".r.old-mine.json", f".r.old-{dead}.txt",
                f".r.tmp-{dead}", f".rr.tmp-{dead}.json", f".r.tmp-{dead}.json.bak",
                ".r.tmp-99999999999999999999.json", ".r.old-0.json"]
        for name in debris + kept:
            (tmp_path / name).write_text("x")
        (tmp_path / f".r.tmp-{dead}1.json").mkdir()  # a folder of that pattern: a user's
        os.symlink(tmp_path / ".r.old-mine.json", tmp_path / f".r.old-{dead}2.json")
        write_json(report, {"new": 1})
        left = sorted(p.name for p in tmp_path.iterdir())
        assert left == sorted([*kept, "r.json", f".r.tmp-{dead}1.json",
                               f".r.old-{dead}2.json"])
        assert json.loads(report.read_text()) == {"new": 1}
    finally:
        live.kill()
        live.wait()


NAME_PARTS = st.sampled_from([".", "r", "json", "tmp", "old", "-", "1", "x", ".json", ".r."])


@settings(max_examples=60, deadline=None)
@given(names=st.lists(st.lists(NAME_PARTS, min_size=1, max_size=7).map("".join),
                      max_size=8, unique=True),
       role=st.sampled_from(["tmp", "old"]))
def test_only_a_dead_writers_exact_names_are_removed(tmp_path_factory, names, role):
    """Generated names near the pattern: exactly `.r.ROLE-DEADPID.json` goes, nothing else."""
    folder = tmp_path_factory.mktemp("names")
    dead = _dead_pid()
    exact = f".r.{role}-{dead}.json"
    names = [n.replace("1", str(dead)) for n in names if n not in ("r.json", ".", "..")]
    names = sorted(set(names) | {exact})
    for name in names:
        (folder / name).write_text("x")
    removed = remove_dead_leftovers(folder / "r.json")
    assert [p.name for p in removed] == [exact]
    assert sorted(p.name for p in folder.iterdir()) == [n for n in names if n != exact]


def test_a_kill_9_among_the_renames_never_leaves_a_new_map_with_an_old_report(
        small_map, scene_dir, tmp_path):
    """J3: pseudo-label's renames put the report in first and the map last, so a kill -9
    between them leaves the old map (its own record of what it is) beside a new report,
    never a new map beside an old report; the next run removes everything it left."""
    out, report = tmp_path / "m", tmp_path / "r.json"
    argv = [sys.executable, "-m", "slamreloc.cli", "pseudo-label", str(small_map.root),
            str(scene_dir), "--out", str(out), "--report", str(report), "--rounds", "1",
            "--epochs", "1"]
    first = subprocess.run(argv, cwd=tmp_path, env=INSTALLED, capture_output=True, text=True,
                           timeout=600)
    assert first.returncode == 0, first.stderr
    old_map, old_report = _tree(out), report.read_bytes()
    killed = subprocess.run([*argv[:-1], "2"], cwd=tmp_path, capture_output=True, text=True,
                            env={**INSTALLED, "SLAMRELOC_TEST_CRASH_AT": "before-swap"}, timeout=600)
    assert killed.returncode == -signal.SIGKILL, killed.stderr
    assert report.read_bytes() != old_report  # the files went in first
    assert _tree(out) == old_map
    again = subprocess.run(argv, cwd=tmp_path, env=INSTALLED, capture_output=True, text=True,
                           timeout=600)
    assert again.returncode == 0, again.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m", "r.json"]


# ---- export --colmap: its swap goes back too -----------------------------------------------
def test_an_exported_model_goes_back_when_a_later_output_cannot(small_map, tmp_path):
    """`export --colmap`'s model swap returns its undo: a later folder output of the same
    block that cannot be put in place leaves the model exported before byte-identical."""
    from slamreloc.map.export import export_map

    model = tmp_path / "model"
    export_map(small_map.root, colmap=model, progress=False)
    before = _tree(model)
    (model / "images.txt").read_text()

    def refused() -> None:
        raise OSError(1, "Operation not permitted", str(tmp_path / "later"))

    with pytest.raises(OSError, match="later"):
        with outputs_together():
            export_map(small_map.root, colmap=model, ply=tmp_path / "p.ply", progress=False)
            commit_output(refused, lambda: None, folder=True)
    assert _tree(model) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["model"]  # no leftover, no new ply


def test_a_killed_exports_model_folders_go_with_the_next_export(small_map, tmp_path):
    from slamreloc.map.export import export_map

    model = tmp_path / "model"
    export_map(small_map.root, colmap=model, progress=False)
    dead = _dead_pid()
    for role in ("tmp", "old"):  # as a kill -9 inside the swap leaves them
        os.mkdir(tmp_path / f".model.{role}-{dead}")
        for f in model.iterdir():
            (tmp_path / f".model.{role}-{dead}" / f.name).write_bytes(f.read_bytes())
    users = tmp_path / f".model.old-{dead}0"  # a model with a user's note: not debris
    users.mkdir()
    (users / "notes.txt").write_text("mine\n")
    export_map(small_map.root, colmap=model, progress=False)
    assert sorted(p.name for p in tmp_path.iterdir()) == [users.name, "model"]


# ---- minor: '-' as an output, the training device ------------------------------------------
def test_a_dash_is_no_output_file(small_map, scene_dir, tmp_path, monkeypatch):
    from tests.fuzzing import run_cli

    monkeypatch.chdir(tmp_path)
    code, err = run_cli(["evaluate", str(small_map.root), str(scene_dir), "--split", "query",
                         "--method", "matching", "--report", "-"])
    assert code == 2 and err.count("\n") == 1 and "--report must name a file" in err, err
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("device", ["banana", "", 5, "CPU", "cuda:0"])
def test_a_maps_training_device_is_a_device_type(small_map, tmp_path, device):
    import shutil

    from slamreloc.map.scene_map import SceneMap

    root = tmp_path / "m"
    shutil.copytree(small_map.root, root)
    meta_path = root / "slamreloc_map.json"
    meta = json.loads(meta_path.read_text())
    meta["train"]["device"] = device
    meta_path.write_text(json.dumps(meta))
    with pytest.raises(InputError, match="'train.device' must be a torch device type"):
        SceneMap.load(root)


# ---- the instant between a command's end and its exit --------------------------------------
def test_the_program_ignores_signals_once_its_command_has_ended():
    """A SIGTERM landing after an interrupted command has ended, while it says so and exits,
    ended the program by the signal with nothing said (status -15): from the command's end the
    program ignores SIGTERM and SIGINT (its outputs are already whole or as they were)."""
    code = ("import atexit, signal, sys\n"
            "from slamreloc import cli\n"
            "def seen(): print('TERM', signal.getsignal(signal.SIGTERM) is signal.SIG_IGN,"
            " 'INT', signal.getsignal(signal.SIGINT) is signal.SIG_IGN, flush=True)\n"
            "atexit.register(seen)\n"
            "def cut(): raise KeyboardInterrupt\n"
            "cli._run_app = cut\n"
            "sys.argv = ['slamreloc', '--help']\n"
            "cli.run()\n")
    proc = subprocess.run([sys.executable, "-c", code], cwd=REPO, env=ENV,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 130, proc.stderr
    assert proc.stdout.strip() == "TERM True INT True" and proc.stderr == "interrupted\n"
