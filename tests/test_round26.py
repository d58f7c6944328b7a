"""Issue 43, attack round 25's notes and round 26: a command that fails writes no empty folders
(`outputs.make_parents` / `remove_made`); a server started on a learned maps' folder cleans what
a server killed while saving there left (`map.lock.clean_maps_folder`), and nothing else."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from slamreloc.service.server import ServeConfig, start_server
from tests.fuzzing import run_cli
from tests.test_cli_round5 import one_line_exit_2


def test_a_failed_pseudo_label_leaves_no_folders_it_made(small_map, scene_dir, tmp_path):
    """Round 25, N5: `pseudo-label --out a/b/c/new` failing at the dataset's split left the
    empty folders a/b/c it had made."""
    kept = tmp_path / "kept"
    kept.mkdir()
    out = kept / "a" / "b" / "c" / "new"
    one_line_exit_2(["pseudo-label", str(small_map.root), str(scene_dir), "--out", str(out),
                     "--report", str(kept / "r" / "r.json"), "--split", "seq-09"],
                    "unknown split")
    assert sorted(os.listdir(kept)) == []  # the folder that was there is kept, empty


def test_a_file_output_made_in_new_folders_keeps_them(small_map, tmp_path):
    """The other side: outputs written into folders the command made keep those folders."""
    tum, ply = tmp_path / "x" / "y" / "t.tum", tmp_path / "p" / "q" / "c.ply"
    code, err = run_cli(["export", str(small_map.root), "--tum", str(tum), "--ply", str(ply)])
    assert code == 0, err
    assert tum.is_file() and ply.is_file()


_KILLED_SAVE = """
import os, shutil, signal, sys
from pathlib import Path
from slamreloc.map.lock import map_write_lock
from slamreloc.io.outputs import temp_dir_path
seed, out = Path(sys.argv[1]), Path(sys.argv[2])
with map_write_lock(out):
    shutil.copytree(seed, temp_dir_path(out))  # the new map, half written
    os.kill(os.getpid(), signal.SIGKILL)
"""


def test_a_server_cleans_a_save_a_killed_server_left(small_map, tmp_path):
    """Round 25, N4: a server killed while writing learned map NAME left `.NAME.lock` and
    `.NAME.tmp-PID/` (a regressor each) until a session saved NAME again; a name never saved
    again kept them for good. The next server on that folder cleans them at start; a user's
    hidden files of like names are kept."""
    folder = tmp_path / "learned"
    folder.mkdir()
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    proc = subprocess.run([sys.executable, "-c", _KILLED_SAVE, str(small_map.root),
                           str(folder / "k")], env=env, capture_output=True, timeout=120)
    assert proc.returncode == -signal.SIGKILL, proc.stderr
    debris = sorted(os.listdir(folder))
    assert debris[0] == ".k.lock" and debris[1].startswith(".k.tmp-"), debris
    (folder / ".notes.lock").write_text("2024\nbudget\n")  # a user's, not a writer's record
    (folder / ".photos.tmp-123").mkdir()
    (folder / ".photos.tmp-123" / "me.jpg").write_bytes(b"\xff\xd8 a photo")
    running = start_server({}, ServeConfig(port=0, watch_s=0, learned_maps=folder))
    try:
        assert sorted(os.listdir(folder)) == [".notes.lock", ".photos.tmp-123"]
        assert (folder / ".notes.lock").read_text() == "2024\nbudget\n"
    finally:
        running.stop()
    shutil.rmtree(folder)


# ---- round 25, N3: a POINTS2D line's fast check ----------------------------------------------
_DIGITS = st.text("0123456789", min_size=1, max_size=4)
_COORD = st.builds(lambda sign, whole, frac, exp: f"{sign}{whole}{frac}{exp}",
                   st.sampled_from(["", "-", "+"]), _DIGITS,
                   st.sampled_from(["", ".", ".5", ".25"]),
                   st.sampled_from(["", "e0", "e-7", "e+38", "e99", "e100", "e150", "e199",
                                    "e200", "e308", "e400", "E-400", "e-999"]))
_ID = st.sampled_from(["-1", "0", "7", "+3", "-2", "4294967295", "123456789", "1234567890"])


@given(st.lists(st.tuples(_COORD, _COORD, _ID), min_size=1, max_size=6))
@settings(max_examples=300, deadline=None)
def test_the_fast_points2d_check_takes_only_what_the_word_rule_takes(triples):
    """A POINTS2D line is matched whole by one pattern where it can be (3-digit exponents now
    included: a 45 MB line of them took 13.5 s word by word); what the pattern takes, the
    number rule applied a word at a time must take too (finite, ids in range)."""
    from slamreloc.datasets.colmap_check import _PLAIN_POINTS, _check_points

    line = " ".join(" ".join(t) for t in triples).encode()
    if _PLAIN_POINTS.fullmatch(line):
        for x, y, point3d_id in triples:
            assert np.isfinite(float(x)) and np.isfinite(float(y))
            assert -1 <= int(point3d_id) < 2 ** 32
        _check_points(Path("images.txt"), 1, line, 0, len(line))  # the same verdict
