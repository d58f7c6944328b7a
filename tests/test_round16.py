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


def test_a_render_waits_for_another_rendering_the_same_scene(tmp_path):
    """Two processes asked for the same scene at once: the second waits for the first (it
    holds the write lock) and takes its scene; neither fails, nothing is left beside it."""
    out = tmp_path / "scene"
    procs = [subprocess.Popen([sys.executable, "-c", RENDER, str(out)], env=ENV,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for _ in range(2)]
    results = [p.communicate(timeout=300) for p in procs]
    assert [p.returncode for p in procs] == [0, 0], [err for _, err in results]
    assert all(o.strip() == "rendered" for o, _ in results)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene"]
    assert _frames_in(out) == sum(TINY.counts().values())


def test_a_scene_is_not_rendered_where_another_kind_of_writer_holds_the_folder(tmp_path):
    """A scene aimed at a folder another command is writing (a map being trained there) is
    refused at once, naming the folder and the writer; the scene renderer waits only for
    another renderer."""
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
