"""No writing command changes anything that is not its own output (issue 43).

Every writing command (export, sfm, map, pseudo-label, slam, evaluate) aimed at its inputs (the
map, the dataset, the dataset and pose file the map records), at a foreign non-empty folder, at
a named pipe or under a regular file must exit 2 with one line, before any work, and leave the
bytes of every file of the work tree as they were."""

from __future__ import annotations

import hashlib
import json
import os
import stat
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from slamreloc.errors import InputError
from slamreloc.io.outputs import check_outputs
from slamreloc.map.format import META
from tests.fuzzing import fuzz_settings, run_cli
from tests.test_fuzz_inputs import _tiny_map, make_sevenscenes


def tree_digest(root: Path) -> dict[str, str]:
    """Path -> SHA-256 (or the kind of a non-regular entry) of everything under `root`."""
    out = {}
    for dirpath, dirnames, filenames in os.walk(root):
        for name in dirnames + filenames:
            p = Path(dirpath) / name
            mode = p.lstat().st_mode
            rel = str(p.relative_to(root))
            if stat.S_ISREG(mode):
                out[rel] = hashlib.sha256(p.read_bytes()).hexdigest()
            else:
                out[rel] = "dir" if stat.S_ISDIR(mode) else f"mode {stat.S_IFMT(mode)}"
    return out


@pytest.fixture(scope="module")
def world(tmp_path_factory) -> Path:
    """The map (recording the dataset `recorded` and the pose file `recorded_poses.txt`), the
    command's dataset `ds`, foreign folders, a pipe and a plain file."""
    w = tmp_path_factory.mktemp("outputs_safe")
    recorded = make_sevenscenes(w / "recorded")
    make_sevenscenes(w / "ds")
    (w / "recorded_poses.txt").write_text("seq-01/frame-000000 0 0 0 0 0 0 1\n")
    m = _tiny_map(w / "map")
    meta = json.loads((m / META).read_text())
    meta["dataset"] = {"root": str(recorded.resolve()), "kind": "7scenes", "split": "train",
                       "metric": True, "poses": str((w / "recorded_poses.txt").resolve())}
    (m / META).write_text(json.dumps(meta))
    (w / "foreign" / "images").mkdir(parents=True)
    (w / "foreign" / "notes.txt").write_text("mine\n")
    (w / "foreign" / "images" / "a.png").write_bytes(b"not really")
    model = w / "model_and_more"  # a COLMAP model with the user's files beside it
    (model / "images").mkdir(parents=True)
    for name in ("cameras.txt", "images.txt", "points3D.txt", "notes.txt"):
        (model / name).write_text(f"# {name}\n")
    os.mkfifo(w / "fifo")
    (w / "notes.txt").write_text("a file, not a folder\n")
    return w


# paths no output may take: (relative path, what it is). Folder outputs are refused at each;
# file outputs at each too (a folder, an input file, a pipe, under a file or a pipe).
INPUT_TARGETS = ["map", f"map/{META}", "map/regressor.npz", "ds", "ds/seq-02",
                 "ds/seq-01/frame-000000.pose.txt", "recorded", "recorded/TrainSplit.txt",
                 "recorded/seq-01/frame-000001.pose.txt", "recorded_poses.txt"]
OTHER_TARGETS = ["foreign", "model_and_more", "fifo", "notes.txt/r.json", "fifo/r.json",
                 "notes.txt/a/b", "foreign/images/a.png", "foreign/notes.txt"]
TARGETS = INPUT_TARGETS + OTHER_TARGETS

# (command, argv with OUT for the target; R: a harmless report path)
COMMANDS = {
    "export colmap": ["export", "{map}", "--dataset", "{ds}", "--colmap", "OUT"],
    "export ply": ["export", "{map}", "--dataset", "{ds}", "--ply", "OUT"],
    "export tum": ["export", "{map}", "--dataset", "{ds}", "--tum", "OUT"],
    "sfm": ["sfm", "{ds}", "--out", "OUT"],
    "map": ["map", "{ds}", "--out", "OUT"],
    "pseudo-label out": ["pseudo-label", "{map}", "{ds}", "--out", "OUT", "--report", "R"],
    "pseudo-label report": ["pseudo-label", "{map}", "{ds}", "--out", "{w}/new_map",
                            "--report", "OUT"],
    "slam report": ["slam", "{ds}", "--map", "{map}", "--report", "OUT"],
    "slam trajectory": ["slam", "{ds}", "--map", "{map}", "--report", "R",
                        "--trajectory", "OUT"],
    "evaluate report": ["evaluate", "{map}", "{ds}", "--report", "OUT"],
    "evaluate plot": ["evaluate", "{map}", "{ds}", "--report", "R", "--plot", "OUT"],
}
# the map command has no map among its inputs: an existing map folder is its kind of output,
# replaced (its files, the recorded dataset and pose file are refused as not a map folder)
NOT_REFUSED = {("map", "map")}


def _argv(world: Path, command: str, target: str) -> list[str]:
    fill = {"map": str(world / "map"), "ds": str(world / "ds"), "w": str(world)}
    return [str(world / target) if a == "OUT" else str(world / "r.json") if a == "R"
            else a.format(**fill) for a in COMMANDS[command]]


def _refused(world: Path, argv: list[str]) -> str:
    before = tree_digest(world)
    code, err = run_cli(argv, hang_s=60)
    assert code == 2, (argv, code, err)
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), (argv, err)
    assert tree_digest(world) == before, argv
    return lines[0]


CASES = [(c, t) for c in COMMANDS for t in TARGETS if (c, t) not in NOT_REFUSED]


@pytest.mark.parametrize("command,target", CASES)
def test_outputs_never_replace_what_is_not_theirs(world, command, target):
    _refused(world, _argv(world, command, target))


# a path under a bad target: nested names under an input folder, a file or a pipe
_NAME = st.text("abz.-_0", min_size=1, max_size=6).filter(lambda s: s not in (".", ".."))


@fuzz_settings(40)
@given(command=st.sampled_from(sorted(COMMANDS)),
       base=st.sampled_from(["map", "ds", "ds/seq-01", "recorded", "recorded/seq-02",
                             "notes.txt", "fifo", "recorded_poses.txt", f"map/{META}"]),
       tail=st.lists(_NAME, min_size=1, max_size=3))
def test_generated_paths_under_inputs_files_and_pipes(world, command, base, tail):
    if command == "map" and base.startswith(("map", "recorded")):
        return  # no map among its inputs: a new map folder there is not refused
    _refused(world, _argv(world, command, "/".join([base, *tail])))


def test_the_examples_of_issue_43(world):
    """export into a folder with notes.txt and images/, --tum over a pose file of the dataset
    the map records, --colmap into that dataset; a report under a regular file."""
    for target in ("foreign", "model_and_more"):
        line = _refused(world, _argv(world, "export colmap", target))
        assert "not empty" in line and "--colmap" in line
    line = _refused(world, _argv(world, "export tum", "recorded/seq-01/frame-000000.pose.txt"))
    assert "the dataset the map records" in line and "--tum" in line
    line = _refused(world, _argv(world, "export colmap", "recorded/sparse"))
    assert "the dataset the map records" in line
    line = _refused(world, _argv(world, "slam report", "notes.txt/r.json"))
    assert "--report" in line and f"its parent {world / 'notes.txt'} is a file" in line


def test_ply_and_plot_replace_only_files_they_wrote(world, tmp_path):
    """export --ply and evaluate --plot replace their own earlier output (marked in the PLY
    header / the PNG's text), never a foreign PLY, PNG or JSON, and --plot must name a .png
    before any work (attack round 4: another map's slamreloc_map.json and a dataset's frame
    image were replaced)."""
    ply, plot, report = tmp_path / "p.ply", tmp_path / "p.png", tmp_path / "r.json"
    export = ["export", str(world / "map"), "--ply", str(ply)]
    evaluate = ["evaluate", str(world / "map"), str(world / "ds"), "--report", str(report),
                "--plot", str(plot)]
    for argv in (export, export, evaluate, evaluate):
        code, err = run_cli(argv)
        assert code == 0, (argv, err)
    other = tmp_path / "other"
    other.mkdir()
    (other / "x.ply").write_bytes(b"ply\nformat ascii 1.0\nelement vertex 0\nend_header\n")
    (other / "x.png").write_bytes(plot.read_bytes().replace(b"slamreloc", b"elsewhere"))
    (other / "x.json").write_text("{}")
    for argv in ([*export[:2], "--ply", str(other / "x.ply")],
                 [*export[:2], "--ply", str(other / "x.json")],
                 [*evaluate[:5], "--plot", str(other / "x.png")]):
        line = _refused(other, argv)
        assert "refusing to replace it" in line, line
    line = _refused(tmp_path, [*evaluate[:5], "--plot", str(tmp_path / "p.json")])
    assert "--plot" in line and ".png" in line


def test_only_a_colmap_model_export_wrote_and_nobody_changed_is_replaced(world, tmp_path):
    """The one folder export replaces: its own model, as it wrote it (the mark's digests). A
    model another tool wrote (a COLMAP dataset's), one edited since, or one with anything
    beside it is refused, and left byte for byte."""
    from slamreloc.map.export import EXPORT_MARK, is_colmap_model

    new = tmp_path / "new"
    argv = ["export", str(world / "map"), "--colmap", str(new)]
    for _ in range(2):
        code, err = run_cli(argv)
        assert code == 0, err
        assert is_colmap_model(new)
    assert sorted(p.name for p in new.iterdir()) == [
        "cameras.txt", "images.txt", "points3D.txt", EXPORT_MARK]
    foreign = tmp_path / "foreign"  # the same model files, not marked: a COLMAP dataset's
    foreign.mkdir()
    for p in new.iterdir():
        if p.name != EXPORT_MARK:
            (foreign / p.name).write_bytes(p.read_bytes())
    edited = tmp_path / "edited"
    edited.mkdir()
    for p in new.iterdir():
        (edited / p.name).write_bytes(p.read_bytes())
    with open(edited / "images.txt", "a") as f:
        f.write("# my note\n")
    extra = tmp_path / "extra"
    extra.mkdir()
    for p in new.iterdir():
        (extra / p.name).write_bytes(p.read_bytes())
    (extra / "images").mkdir()
    for folder in (foreign, edited, extra):
        assert not is_colmap_model(folder)
        before = {p.name: p.read_bytes() for p in folder.iterdir() if p.is_file()}
        code, err = run_cli(["export", str(world / "map"), "--colmap", str(folder)])
        assert code == 2 and "refusing to replace it" in err, err
        assert {p.name: p.read_bytes() for p in folder.iterdir() if p.is_file()} == before


def test_check_outputs_names_the_option_and_the_problem(tmp_path):
    (tmp_path / "f").write_text("x")
    os.mkfifo(tmp_path / "p")
    cases = {tmp_path / "f" / "r.json": "its parent",
             tmp_path / "f" / "a" / "b" / "r.json": "its parent",
             tmp_path / "p" / "r.json": "its parent",
             tmp_path / "p": "not a regular file"}
    for out, words in cases.items():
        with pytest.raises(InputError) as err:
            check_outputs({"`report`": out}, {})
        assert words in str(err.value) and "`report`" in str(err.value)
    # the temporary file the atomic write uses beside the output: a pipe there would block
    tmp = tmp_path / f".r.tmp-{os.getpid()}.json"
    os.mkfifo(tmp)
    with pytest.raises(InputError, match="temporary path"):
        check_outputs({"`report`": tmp_path / "r.json"}, {})
    with pytest.raises(InputError, match="not empty"):
        check_outputs({"`out`": tmp_path}, {}, folders={"`out`": None})


# --- the error is the last line on stderr, after any progress bar ---------------------------

def _cli_subprocess(argv: list[str]) -> tuple[int, list[str]]:
    import subprocess
    import sys

    repo = Path(__file__).resolve().parents[1]
    res = subprocess.run([sys.executable, "-m", "slamreloc.cli", *argv], cwd=repo,
                         capture_output=True, text=True, timeout=300)
    return res.returncode, res.stderr.splitlines()


def test_an_error_during_a_progress_bar_is_the_last_line(world, tmp_path):
    """`slam --odometry TRAJ` with a trajectory that misses the dataset's frames fails while
    the `slam` bar is up, as does `export` on a dataset whose second image is damaged while
    `colouring points` is: the bar is never drawn again after the error line."""
    traj = tmp_path / "traj.txt"
    traj.write_text("1000.0 0 0 0 0 0 0 1\n1000.1 0 0 0 0 0 0 1\n")
    code, lines = _cli_subprocess(["slam", str(world / "ds"), "--map", str(world / "map"),
                                   "--odometry", str(traj), "--report", str(tmp_path / "r.json")])
    assert code == 2 and lines and lines[-1].startswith("error: "), lines
    assert str(traj) in lines[-1] and "no pose" in lines[-1]
    assert not (tmp_path / "r.json").exists()

    import shutil

    ds = tmp_path / "ds"
    shutil.copytree(world / "ds", ds)
    bad = ds / "seq-01" / "frame-000001.color.png"
    bad.write_bytes(bad.read_bytes()[:40])
    code, lines = _cli_subprocess(["export", str(world / "map"), "--dataset", str(ds),
                                   "--ply", str(tmp_path / "points.ply")])
    assert code == 2 and lines and lines[-1].startswith("error: "), lines
    assert str(bad) in lines[-1]
    assert not (tmp_path / "points.ply").exists()


def test_progress_bars_left_up_are_erased(capsys):
    """The two ways a bar is left unfinished: its consumer fails (the generator is closed
    whenever it is collected, possibly after the error is printed) and its items fail."""
    from slamreloc.runtime import progress

    def consumer():
        for i in progress.track(range(10), "consumer fails", total=10):
            if i == 3:
                raise ValueError("boom")
            yield i

    with pytest.raises(ValueError):
        list(consumer())
    progress.stop_bars()  # what the CLI does before it prints the error

    def items():
        yield 1
        raise ValueError("items fail")

    with pytest.raises(ValueError):
        list(progress.track(items(), "items fail", total=2))
    assert not progress._SHOWN
    assert capsys.readouterr().err == ""
