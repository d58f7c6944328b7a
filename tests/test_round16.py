"""Issue 43, what the fifteenth attack round left (L5: a killed `demo` left its partial scene
render beside the scene, one more per killed run) and what the sixteenth found."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from slamreloc.errors import InputError
from slamreloc.synthetic import SceneConfig, render_scene

REPO = Path(__file__).resolve().parents[1]
ENV = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"} | {"OMP_NUM_THREADS": "1"}
TINY = SceneConfig(width=160, height=120, fx=131.25, fy=131.25, cx=79.5, cy=59.5,
                   n_map=40, n_query=8, n_kidnap=8, n_unlabelled=8)
RENDER = ("import sys\nfrom pathlib import Path\nfrom slamreloc.synthetic import SceneConfig, "
          "render_scene\nrender_scene(Path(sys.argv[1]), SceneConfig(width=160, height=120, "
          "fx=131.25, fy=131.25, cx=79.5, cy=59.5, n_map=40, n_query=8, n_kidnap=8, "
          "n_unlabelled=8))\nprint('rendered', flush=True)\n")


def _frames_in(folder: Path) -> int:
    return sum(1 for _ in folder.glob("seq-*/frame-*.color.png"))


def _killed_mid_render(out: Path, argv: list[str]) -> None:
    """Start `argv` (which renders the scene `out`) and kill -9 it once its temporary holds
    frames: the render cut short, as a user's kill or a power loss leaves it."""
    proc = subprocess.Popen(argv, env=ENV, cwd=out.parent, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 120
    try:
        while time.monotonic() < deadline and proc.poll() is None:
            temps = list(out.parent.glob(f".{out.name}.tmp-*"))
            if temps and _frames_in(temps[0]) >= 3:
                break
            time.sleep(0.02)
        assert proc.poll() is None, "the render ended before it could be killed"
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()


def test_a_killed_demos_partial_render_goes_with_the_next_render(tmp_path):
    """L5: `demo` killed while it renders left `.scene.tmp-PID` (11 MB at full size), and
    every killed run one more. The scene is written under its folder's write lock; the next
    render removes what a killed render left, and only that: a folder of a like name that
    holds a user's file stays."""
    work = tmp_path / "work"
    work.mkdir()
    out = work / "scene"
    _killed_mid_render(out, [sys.executable, "-m", "slamreloc.cli", "demo", "--workdir",
                             str(work), "--no-viewer"])
    left = list(work.glob(".scene.tmp-*"))
    assert len(left) == 1 and _frames_in(left[0]) >= 3  # what the kill left, as round 15 saw
    users = work / ".scene.tmp-77"
    (users / "seq-01").mkdir(parents=True)
    (users / "seq-01" / "notes.txt").write_text("mine")

    render_scene(out, TINY)

    assert sorted(p.name for p in work.iterdir()) == [".scene.tmp-77", "scene"]
    assert (users / "seq-01" / "notes.txt").read_text() == "mine"
    assert _frames_in(out) == sum(TINY.counts().values())


def test_a_second_render_of_a_scene_is_refused_at_once_naming_the_first(tmp_path):
    """Round 16, P3: a second renderer of the same scene waited for the first with no
    deadline and no message (forever, behind a stopped one). It is refused at once, naming
    the process that renders, as every folder writer is; the first finishes its scene, and
    nothing is left beside it."""
    out = tmp_path / "scene"
    first = subprocess.Popen([sys.executable, "-c", RENDER, str(out)], env=ENV,
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 120
        while not list(tmp_path.glob(".scene.tmp-*/seq-01/frame-*")):
            assert first.poll() is None and time.monotonic() < deadline
            time.sleep(0.02)
        with pytest.raises(InputError, match=rf"scene: another process \(pid {first.pid}\) is "
                                             r"writing this scene; try again"):
            render_scene(out, TINY)
    finally:
        output, err = first.communicate(timeout=300)
    assert first.returncode == 0 and output.strip() == "rendered", err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene"]
    assert _frames_in(out) == sum(TINY.counts().values())


def test_a_writer_met_before_it_has_written_its_lock_record_is_named(tmp_path):
    """Round 16, P1: a writer that had taken a folder's lock but not yet written its record
    (`PID\nWHAT\n`, written just after) was told as "pid ?, this map", whatever it wrote.
    The record is read again until it is there: the refusal names the holder and its kind."""
    out = tmp_path / "scene"
    holder = subprocess.Popen(
        [sys.executable, "-c", "import fcntl, os, sys, time\n"
         "fd = os.open(sys.argv[1], os.O_RDWR | os.O_CREAT, 0o644)\n"
         "fcntl.flock(fd, fcntl.LOCK_EX)\nprint('held', flush=True)\ntime.sleep(0.3)\n"
         "os.pwrite(fd, f'{os.getpid()}\\nthis scene\\n'.encode(), 0)\ntime.sleep(60)\n",
         str(tmp_path / ".scene.lock")], env=ENV, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(InputError, match=rf"another process \(pid {holder.pid}\) is "
                                             "writing this scene"):
            render_scene(out, TINY)
    finally:
        holder.kill()
        holder.wait()


@pytest.mark.parametrize("target", ["empty", "missing"])
def test_a_scene_is_never_rendered_through_a_link(tmp_path, target):
    """Round 16, P2: `demo` with WORKDIR/scene a symbolic link (to an empty folder, or to
    nothing) rendered every frame, then failed with a raw `[Errno 20] Not a directory`
    naming its own temporary. A link is refused before any work, as every folder output's
    is, and left as it was."""
    from tests.fuzzing import run_cli

    work = tmp_path / "w"
    work.mkdir()
    (tmp_path / "empty").mkdir()
    (work / "scene").symlink_to(tmp_path / target)
    started = time.monotonic()
    code, err = run_cli(["demo", "--workdir", str(work), "--no-viewer"])
    last = err.strip().splitlines()[-1]
    assert code == 2 and last == (f"error: {work / 'scene'}: is a symbolic link (to "
                                  f"{tmp_path / target}); a scene is rendered into a folder, "
                                  "never through a link: give a plain path"), err
    assert time.monotonic() - started < 30  # before the render (410 frames), not after
    assert os.readlink(work / "scene") == str(tmp_path / target)
    assert sorted(p.name for p in work.iterdir()) == ["scene"]
    assert list((tmp_path / "empty").iterdir()) == []


def test_a_scene_is_not_rendered_where_another_kind_of_writer_holds_the_folder(tmp_path):
    """A scene aimed at a folder another command is writing (a map being trained there) is
    refused at once, naming the folder and the writer."""
    out = tmp_path / "m"
    holder = subprocess.Popen(
        [sys.executable, "-c", "import sys, time\nfrom slamreloc.map.lock import "
         "map_write_lock\nwith map_write_lock(sys.argv[1]):\n    print('held', flush=True)\n"
         "    time.sleep(60)\n", str(out)], env=ENV, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(InputError, match=r"m: another process \(pid \d+\) is writing "
                                             r"this map"):
            render_scene(out, TINY)
    finally:
        holder.kill()
        holder.wait()
    assert not out.exists()


# ---- round 15's minor findings (M3-M5) -------------------------------------------------------
def test_a_files_second_name_in_the_way_is_refused_before_the_work(tmp_path):
    """M4: a folder at the second name the replaced file is kept under
    (`.t.names.old-PID.txt`, this process's id) was refused only at the commit, after the
    work; like the temporary, it is now refused when the outputs are checked. A killed
    writer's unheld file of that name is no refusal (the writer removes it)."""
    from slamreloc.io.outputs import check_outputs, temp_file_path

    out = tmp_path / "t.names.txt"
    out.write_text("old names\n")
    second = temp_file_path(out, "old")
    second.mkdir()
    with pytest.raises(InputError, match=r"its temporary path .*\.t\.names\.old-\d+\.txt is "
                                         r"in the way.* live writer's in another PID namespace"):
        check_outputs({"--trajectory's names file": out}, {})
    second.rmdir()
    second.write_text("a killed writer's")
    check_outputs({"--trajectory's names file": out}, {})
    assert out.read_text() == "old names\n"


def test_sfm_never_removes_a_file_put_into_its_output_while_it_ran(scene_dir, tmp_path):
    """M5: sfm removed the empty output folder it was given, then renamed its dataset in: a
    kill between the two lost the folder and the run's work, and a file put into the folder
    meanwhile made an unclear error. One rename now puts the dataset over the empty folder;
    a file put there meanwhile is kept, and the run says so in one line."""
    import shutil
    import threading

    from slamreloc.datasets import load_dataset
    from tests.fuzzing import run_cli

    photos = tmp_path / "photos"
    photos.mkdir()
    # 20 frames, as tests/test_sfm.py: 12 registered on an EPYC but only 3 on an AMX Xeon
    for frame in load_dataset(scene_dir).frames("seq-01")[:20]:
        shutil.copyfile(frame.image_path, photos / f"{frame.name.split('/')[-1]}.png")
    out = tmp_path / "o"
    out.mkdir()

    def put_a_file_in_when_sfm_has_started():
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            if any(tmp_path.glob(".o.tmp-*/images/*")):
                (out / "notes.txt").write_text("mine")
                return
            time.sleep(0.01)

    writer = threading.Thread(target=put_a_file_in_when_sfm_has_started)
    writer.start()
    code, err = run_cli(["sfm", str(photos), "--out", str(out)], hang_s=300.0)
    writer.join()
    last = err.strip().splitlines()[-1]
    assert code == 2 and last.startswith("error: "), err
    assert "something was put into this folder while sfm ran" in last
    assert (out / "notes.txt").read_text() == "mine" and list(out.iterdir()) == [out / "notes.txt"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["o", "photos"]


# ---- attack round 16, service side ---------------------------------------------------------
def test_a_folders_write_lock_is_held_by_one_thread_at_a_time(tmp_path):
    """S2: the lock was re-entrant for the whole process, so a second thread (a server's load
    cleaning a map's leftovers, while a session saved it) entered at once, or was refused
    naming its own process, and its exit removed the lock file while the first still wrote.
    It is re-entrant within a thread only: another thread waits for it (then gets it, the
    lock file still there for the first), or after `wait_s` is refused, saying so."""
    import threading

    from slamreloc.io.folder_lock import folder_write_lock
    from slamreloc.map.lock import MAP_DEBRIS, map_write_lock

    out = tmp_path / "m"
    events: list[tuple[str, float]] = []
    entered = threading.Event()

    def first():
        with map_write_lock(out):
            with map_write_lock(out):  # re-entrant in its own thread
                entered.set()
                time.sleep(0.5)
                events.append(("first still has the lock file",
                               (tmp_path / ".m.lock").is_file()))
            events.append(("first leaves", time.monotonic()))

    def second():
        assert entered.wait(10)
        with pytest.raises(InputError, match=r"m: another thread of this process \(pid \d+\) "
                                             r"is writing it; try again"):
            with folder_write_lock(out, "this map", MAP_DEBRIS, wait_s=0.1):
                pass
        with map_write_lock(out):
            events.append(("second enters", time.monotonic()))

    threads = [threading.Thread(target=first), threading.Thread(target=second)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(30)
    named = dict(events)
    assert named["first still has the lock file"] is True
    assert named["second enters"] >= named["first leaves"]
    assert list(tmp_path.iterdir()) == []
