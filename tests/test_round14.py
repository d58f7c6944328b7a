"""Issue 43, what the thirteenth attack round left: a kill -9 among a command's renames (J3),
export's model swap that could not be undone, `--report -`, the recorded training device, and
the instant between a command's end and its exit."""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from slamreloc.errors import InputError
from slamreloc.io.outputs import commit_output, outputs_together, remove_dead_leftovers, write_json

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


# ---- J3 / K1 / K3 / K5: what a killed writer leaves beside a file output -------------------
HOLD = ("import fcntl, os, sys, time\n"
        "fd = os.open(sys.argv[1], os.O_RDWR | os.O_CREAT | os.O_EXCL, 0o644)\n"
        "fcntl.flock(fd, fcntl.LOCK_EX)\n"
        "print('held', flush=True)\n"
        "time.sleep(60)\n")


def test_a_killed_writers_temporaries_go_with_the_next_write(tmp_path):
    """A kill -9 leaves `.r.tmp-PID.json` (the new report not yet renamed in) and
    `.r.old-PID.json` (the second name of the report it replaced): the next writer of r.json
    removes them, whatever their PID (this process's own, as in a container: K3). A live
    writer's temporary - held with `flock`, here under a PID that is no process of this PID
    namespace, as a writer in another container (K5) - stays, and so do a user's files of a
    like name (a PID with a leading zero: K1), a folder and a link."""
    dead = _dead_pid()
    held = tmp_path / f".r.tmp-{dead}7.json"
    live = subprocess.Popen([sys.executable, "-c", HOLD, str(held)], stdout=subprocess.PIPE,
                            text=True)
    try:
        assert live.stdout.readline().strip() == "held"
        report = tmp_path / "r.json"
        report.write_text("{}")
        debris = [f".r.tmp-{dead}.json", f".r.old-{dead}.json", f".r.old-{os.getpid()}.json",
                  f".r.tmp-{os.getpid()}.json"]
        kept = [".r.old-mine.json", f".r.old-{dead}.txt", f".r.tmp-{dead}",
                f".rr.tmp-{dead}.json", f".r.tmp-{dead}.json.bak", ".r.old-0.json",
                f".r.old-0{dead}.json", ".r.tmp-.json"]
        for name in debris + kept:
            (tmp_path / name).write_text("x")
        (tmp_path / f".r.tmp-{dead}1.json").mkdir()  # a folder of that pattern: a user's
        os.symlink(tmp_path / ".r.old-mine.json", tmp_path / f".r.old-{dead}2.json")
        write_json(report, {"new": 1})
        left = sorted(p.name for p in tmp_path.iterdir())
        assert left == sorted([*kept, "r.json", held.name, f".r.tmp-{dead}1.json",
                               f".r.old-{dead}2.json"])
        assert json.loads(report.read_text()) == {"new": 1}
    finally:
        live.kill()
        live.wait()


NAME_PARTS = st.sampled_from([".", "r", "json", "tmp", "old", "-", "1", "0", "x", ".json",
                              ".r."])
DEBRIS_NAME = re.compile(r"\.r\.(tmp|old)-([1-9][0-9]*)\.json")  # the oracle, written apart


@settings(max_examples=80, deadline=None)
@given(names=st.lists(st.lists(NAME_PARTS, min_size=1, max_size=7).map("".join),
                      max_size=8, unique=True))
def test_only_a_writers_exact_names_are_removed(tmp_path_factory, names):
    """Generated names near the pattern: exactly `.r.tmp-PID.json` / `.r.old-PID.json` (PID
    as a process id is written) go, when no process holds them; nothing else."""
    folder = tmp_path_factory.mktemp("names")
    names = sorted({n for n in names if n not in ("r.json", ".", "..")})
    for name in names:
        (folder / name).write_text("x")
    removed = remove_dead_leftovers(folder / "r.json")
    expected = [n for n in names if (m := DEBRIS_NAME.fullmatch(n)) and int(m[2]) <= 1 << 22]
    assert sorted(p.name for p in removed) == expected
    assert sorted(p.name for p in folder.iterdir()) == [n for n in names if n not in expected]


def test_a_stale_second_name_with_this_writers_pid_never_turns_the_undo_off(tmp_path):
    """K3: a killed writer's `.r.old-PID.json` with this process's PID (a container gives the
    same PID every run) made the second name fail silently: the report was replaced with no
    undo, and a later output that could not be put in place left the new report. Now it is
    removed first, and the report goes back."""
    report = tmp_path / "r.json"
    write_json(report, {"old": 1})
    (tmp_path / f".r.old-{os.getpid()}.json").write_text("a killed writer's")

    def refused():
        raise OSError(1, "Operation not permitted", str(tmp_path / "m"))

    with pytest.raises(OSError, match="not permitted"):
        with outputs_together():
            write_json(report, {"new": 1})
            commit_output(refused, lambda: None, folder=True)
    assert json.loads(report.read_text()) == {"old": 1}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r.json"]


def test_an_output_named_as_another_outputs_temporary_is_refused(small_map, scene_dir,
                                                                  tmp_path):
    """K6: `--trajectory D/.r.tmp-31001.json` beside `--report D/r.json` was taken, and the
    next writer of the report removed it as debris."""
    from tests.fuzzing import run_cli

    code, err = run_cli(["evaluate", str(small_map.root), str(scene_dir), "--split", "query",
                         "--method", "matching", "--report", str(tmp_path / "r.json"),
                         "--trajectory", str(tmp_path / ".r.tmp-31001.json")])
    assert code == 2 and err.count("\n") == 1, err
    assert "--trajectory is named as a writer's temporary or lock" in err, err
    assert list(tmp_path.iterdir()) == []


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
    crash = {**INSTALLED, "SLAMRELOC_TEST_CRASH_AT": "before-swap"}
    killed = subprocess.run([*argv[:-1], "2"], cwd=tmp_path, env=crash, capture_output=True,
                            text=True, timeout=600)
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


def test_a_killed_exports_model_is_put_back_and_its_temporaries_removed(small_map, tmp_path,
                                                                       monkeypatch):
    """K2: a kill between the two renames of the fallback swap left no model at DIR and the
    old one aside; the next export deleted it. Now the next export (under the model's write
    lock) puts it back first, so even a next export that fails leaves the old model; the
    killed export's temporary goes. A folder of a like name with a user's note stays."""
    from slamreloc.map import export

    model = tmp_path / "model"
    export.export_map(small_map.root, colmap=model, progress=False)
    before = _tree(model)
    dead = _dead_pid()
    os.rename(model, tmp_path / f".model.old-{dead}")  # as the kill leaves it
    shutil.copytree(tmp_path / f".model.old-{dead}", tmp_path / f".model.tmp-{dead}")
    users = tmp_path / f".model.old-{dead}0"
    shutil.copytree(tmp_path / f".model.tmp-{dead}", users)
    (users / "notes.txt").write_text("mine\n")

    def cut(*args):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(export, "_write_export_mark", cut)
    with pytest.raises(OSError, match="No space"):
        export.export_map(small_map.root, colmap=model, progress=False)
    assert _tree(model) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == [users.name, "model"]


def test_sfm_cleans_only_what_an_sfm_run_leaves(tmp_path):
    """K7 / K8: `sfm --out O` cleaned up as a map writer does: it moved a map it found at
    `.O.old-PID` into O (then refused O as not empty), and never removed a killed sfm's
    `.O.tmp-PID` (its copies of the photos). Now it removes a killed run's temporary and
    leaves a map of a like name alone."""
    from tests.fuzzing import run_cli
    from tests.test_map_format import make_map

    dead = _dead_pid()
    killed = tmp_path / f".o.tmp-{dead}"
    (killed / "images").mkdir(parents=True)
    (killed / "images" / "a.png").write_bytes(b"a copied photo")
    (killed / "sparse" / "0").mkdir(parents=True)
    aside = make_map(tmp_path / f".o.old-{dead}", tag="a user's")
    photos = tmp_path / "photos"
    photos.mkdir()
    (photos / "one.png").write_bytes(b"not enough for SfM")
    code, err = run_cli(["sfm", str(photos), "--out", str(tmp_path / "o")])
    assert code == 2 and err.count("\n") == 1 and "error:" in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == [aside.name, "photos"]


def test_view_reads_a_dataset_it_is_given_as_every_command_does(small_map, tmp_path):
    """K4: `view --dataset` took any folder that is no dataset and showed the map without
    images, where `export --ply --dataset` refuses it."""
    from tests.fuzzing import run_cli

    (tmp_path / "empty").mkdir()
    code, err = run_cli(["view", str(small_map.root), "--dataset", str(tmp_path / "empty"),
                         "--port", "0"])
    assert code == 2 and err.count("\n") == 1 and "empty" in err, err


# ---- minor: '-' as an output, the training device ------------------------------------------
def test_a_dash_is_no_output_file(small_map, scene_dir, tmp_path, monkeypatch):
    from tests.fuzzing import run_cli

    monkeypatch.chdir(tmp_path)
    code, err = run_cli(["evaluate", str(small_map.root), str(scene_dir), "--split", "query",
                         "--method", "matching", "--report", "-"])
    assert code == 2 and err.count("\n") == 1 and "--report must name a path" in err, err
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("device", ["banana", "", 5, "CPU", "cuda:0"])
def test_a_maps_training_device_is_a_device_type(small_map, tmp_path, device):
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


# ---- S1: reloads hold a bounded number of the server's threads ----------------------------
def test_reloads_waiting_at_once_are_bounded_and_health_answers(tmp_path, monkeypatch):
    """S1: every ReloadMap holds a thread of the server's pool while its map loads, and the
    pool counted one per map at start-up: maps saved by sessions later took threads Health
    needed. Now `max_reloads` wait at once; the next is OVERLOADED at once, naming the bound,
    and Health answers throughout."""
    import threading
    import time

    from slamreloc.proto import relocalizer_pb2 as pb
    from slamreloc.service.server import ServeConfig, start_server
    from tests.test_fuzz_inputs import _tiny_map
    from tests.test_hardening import copy_map
    from tests.test_service_hardening import _call, held_loads

    first = _tiny_map(tmp_path / "a")
    maps = {"a": first, "b": copy_map(first, tmp_path / "b"), "c": copy_map(first, tmp_path / "c")}
    running = start_server(maps, ServeConfig(port=0, watch_s=0, max_reloads=2))
    release = held_loads(monkeypatch)
    waiting = [threading.Thread(target=_call, args=(running.address, "ReloadMap",
                                                    pb.ReloadMapRequest(map=m)))
               for m in ("a", "b")]
    try:
        for thread in waiting:
            thread.start()
        time.sleep(0.5)
        status, kind, details, seconds = _call(running.address, "ReloadMap",
                                               pb.ReloadMapRequest(map="c"))
        assert (status, kind) == ("RESOURCE_EXHAUSTED", "OVERLOADED") and seconds < 1.0
        assert "max_reloads" in details, details
        assert _call(running.address, "Health", pb.HealthRequest())[0] == "OK"
        release.set()
        for thread in waiting:
            thread.join(30)
        assert _call(running.address, "ReloadMap", pb.ReloadMapRequest(map="c"))[0] == "OK"
    finally:
        release.set()
        running.stop()


# ---- attack round 15 -----------------------------------------------------------------------
def test_a_map_moved_aside_with_a_users_file_is_never_removed(small_map, tmp_path):
    """L1: a `.M.old-PID` holding a map and a user's file (written into the map's folder while
    a writer replaced it, then the writer killed) was removed by a reader; it is kept, and put
    back whole where the map is missing. One with only the map's files is debris."""
    from slamreloc.map.scene_map import SceneMap

    root = tmp_path / "m"
    shutil.copytree(small_map.root, root)
    dead = _dead_pid()
    with_note = tmp_path / f".m.old-{dead}"
    shutil.copytree(small_map.root, with_note)
    (with_note / "notes.txt").write_text("mine\n")
    debris = tmp_path / f".m.old-{dead}1"
    shutil.copytree(small_map.root, debris)
    SceneMap.load(root)  # a reader cleans a killed writer's debris
    assert sorted(p.name for p in tmp_path.iterdir()) == [with_note.name, "m"]
    shutil.rmtree(root)  # the map missing: the one moved aside goes back whole
    SceneMap.load(with_note)  # (a map it is)
    from slamreloc.map.lock import map_write_lock

    with map_write_lock(root):
        pass
    assert (root / "notes.txt").read_text() == "mine\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m"]


def test_only_exports_own_model_is_taken_for_a_killed_exports(small_map, tmp_path):
    """L2 / L10: a folder of COLMAP file names (a binary model, or an empty folder) beside
    the model was taken for a killed export's and put back or removed."""
    from slamreloc.map.export import export_map

    model = tmp_path / "model"
    dead = _dead_pid()
    binary = tmp_path / f".model.old-{dead}"
    binary.mkdir()
    for name in ("cameras.bin", "images.bin", "points3D.bin"):
        (binary / name).write_bytes(b"a user's model")
    empty = tmp_path / f".model.old-{dead}1"
    empty.mkdir()
    export_map(small_map.root, colmap=model, progress=False)
    assert sorted(p.name for p in tmp_path.iterdir()) == [binary.name, empty.name, "model"]
    assert (model / "cameras.txt").is_file()


@pytest.mark.parametrize("name", [".t.tmp-31001.txt", ".x.tmp-31001", ".m.old-31001", ".m.lock",
                                  ".r.old-7.names.txt"])
def test_an_output_is_never_named_as_a_writers_temporary(small_map, tmp_path, name):
    """L3: an output named like any writer's temporary or lock was taken, and a later writer
    (or a reader of a map of that name) removed it."""
    from tests.fuzzing import run_cli

    code, err = run_cli(["export", str(small_map.root), "--tum", str(tmp_path / name)])
    assert code == 2 and "named as a writer's temporary or lock" in err, err
    assert list(tmp_path.iterdir()) == []


def test_a_users_file_at_a_lock_path_is_never_taken_for_a_lock(small_map, tmp_path):
    """L7: a user's file at `.x.lock` whose first line is a number was taken for a lock
    record, overwritten and removed."""
    from tests.fuzzing import run_cli

    lock = tmp_path / ".x.lock"
    lock.write_text("2024\nbudget: do not delete\n")
    code, err = run_cli(["export", str(small_map.root), "--colmap", str(tmp_path / "x")])
    assert code == 2 and "not a slamreloc write lock" in err, err
    assert lock.read_text() == "2024\nbudget: do not delete\n"


@pytest.mark.parametrize("out", [".", ".."])
def test_a_folder_output_ends_in_a_name(small_map, tmp_path, monkeypatch, out):
    """L8: `--colmap .` put its lock and temporary inside the output, then refused with a
    message about them."""
    from tests.fuzzing import run_cli

    (tmp_path / "e").mkdir()
    monkeypatch.chdir(tmp_path / "e")
    code, err = run_cli(["export", str(small_map.root), "--colmap", out])
    assert code == 2 and "must end in a name" in err, err
    assert list((tmp_path / "e").iterdir()) == []


def test_an_output_name_leaves_room_for_its_writers_names(scene_dir, tmp_path):
    """L9: `map --out NAME` with a 236-byte name wrote the map, then failed on its training
    checkpoint's longer name beside it."""
    from slamreloc.io.outputs import MAX_OUTPUT_NAME
    from tests.fuzzing import run_cli

    out = tmp_path / ("m" * (MAX_OUTPUT_NAME + 1))
    code, err = run_cli(["map", str(scene_dir), "--out", str(out)])
    assert code == 2 and f"at most {MAX_OUTPUT_NAME}" in err, err
    assert list(tmp_path.iterdir()) == []


def test_a_writer_removes_only_its_own_files_after_its_commit(tmp_path):
    """L6: after renaming its temporary in, a writer removed that name again; a live writer
    of the same PID elsewhere (another container) had made it meanwhile."""
    report = tmp_path / "r.json"
    theirs = tmp_path / f".r.tmp-{os.getpid()}.json"

    def another_writer_makes_the_name() -> None:
        theirs.write_text("another container's writer, alive")

    with outputs_together():
        write_json(report, {"new": 1})
        commit_output(another_writer_makes_the_name, lambda: None)
    assert theirs.read_text() == "another container's writer, alive"
    assert json.loads(report.read_text()) == {"new": 1}
