"""CLI attack round 3 (findings 10-15, 18): values taken silently or by another rule than the
rest. Each bad input ends in one `error:` line naming the option (and file) and exit status 2:

- #10 #11 a `--split` list naming a sequence twice (directly, or through a split or role it
  also names) is refused; roles and splits combine with sequences in a list;
- #12 #13 a `--limit` is a whole number in ASCII digits (`slamreloc.io.numbers`), given once;
  its messages print the bound as it is (a 1000-pixel bound was "0.0 MP");
- #14 `view --port` follows `serve --port`'s rule: 0 to 65535, 0 any free port;
- #15 a `slam` option that has no effect in the combination given is refused, naming both;
- #18 `export --dataset` of another dataset than the map's is refused.

CLI cases run the real command line (`python -m slamreloc.cli`); the rules behind them are
checked in process on generated inputs (hypothesis)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from slamreloc.datasets.base import Dataset
from slamreloc.errors import InputError
from slamreloc.io.limits import (
    LIMIT_MAXIMA,
    MAX_LIMIT,
    InputLimits,
    parse_limits,
    pixels_text,
)
from slamreloc.io.numbers import number_problem
from slamreloc.map.format import META
from tests.test_cli_hardening import cli
from tests.test_cli_hardening import one_error_line as hardening_error_line
from tests.test_fuzz_inputs import _tiny_map, make_sevenscenes

REPO = Path(__file__).resolve().parents[1]
FAST = settings(max_examples=60, deadline=None, derandomize=True, database=None)
LIMIT_NAMES = [f for f in vars(InputLimits()).keys()]


def one_error_line(res: subprocess.CompletedProcess, *words: str) -> str:
    """`test_cli_hardening`'s check, and every setting shown as its flag (no `name`)."""
    line = hardening_error_line(res, *words)
    assert "`" not in line, line
    return line


@pytest.fixture(scope="module")
def work(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("round3")


@pytest.fixture(scope="module")
def tiny_map(work) -> Path:
    return _tiny_map(work / "map")


@pytest.fixture(scope="module")
def dataset(work) -> Path:
    """seq-01 (role map, train split), seq-02 (role query, test split)."""
    return make_sevenscenes(work / "ds")


# --- #10 #11: split lists ---------------------------------------------------------------------

SEQUENCES = [f"seq-{i:02d}" for i in range(1, 6)]
ROLES = {"seq-01": "map", "seq-02": "query", "seq-03": "kidnap", "seq-04": "kidnap"}
SPLITS = {"train": ["seq-01"], "test": ["seq-02", "seq-03"]}


def _dataset() -> Dataset:
    return Dataset(Path("ds"), "synthetic", {s: [] for s in SEQUENCES}, splits=SPLITS,
                   roles=ROLES)


def _sequences_of(item: str) -> list[str]:
    if item == "all":
        return SEQUENCES
    if item in SPLITS:
        return SPLITS[item]
    by_role = [s for s, r in ROLES.items() if r == item]
    return by_role or [item]


NAMES = st.sampled_from(["all", *SPLITS, *sorted(set(ROLES.values())), *SEQUENCES])


@FAST
@given(items=st.lists(NAMES, min_size=1, max_size=5))
def test_a_split_list_is_its_items_sequences_each_once(items):
    """Every item of a list (split, role, sequence, all) stands for its sequences; a list in
    which any sequence comes twice is refused, naming it; any other is their concatenation."""
    split = ",".join(items)
    expected = [s for item in items for s in _sequences_of(item)]
    if len(set(expected)) == len(expected):
        assert _dataset().resolve_split(split) == expected
    else:
        given_by: dict[str, str] = {}
        for item in items:  # the first sequence named again, and by which items
            again = [s for s in _sequences_of(item) if s in given_by]
            if again:
                seq, first = again[0], given_by[again[0]]
                break
            given_by.update((s, item) for s in _sequences_of(item))
        with pytest.raises(InputError) as err:
            _dataset().resolve_split(split)
        assert str(err.value).startswith(f"ds: `split` {split!r} names ")
        assert (f"names '{item}' twice" if first == item else
                f"names sequence '{seq}' twice") in str(err.value)


@FAST
@given(seq=st.sampled_from(SEQUENCES), pad=st.sampled_from(["", " "]))
def test_a_sequence_named_twice_is_refused(seq, pad):
    with pytest.raises(InputError, match=f"names '{seq}' twice"):
        _dataset().resolve_split(f"{seq},{pad}{seq}")


def test_an_unknown_name_in_a_list_is_named_without_contradiction():
    with pytest.raises(InputError) as err:
        _dataset().resolve_split("kidnap,seq-99")
    assert str(err.value).startswith("ds: unknown split or sequence 'seq-99' (in `split` "
                                     "'kidnap,seq-99') (known splits, roles and sequences: ")
    assert _dataset().resolve_split("kidnap,seq-01") == ["seq-03", "seq-04", "seq-01"]
    for empty in ("", ",", "kidnap,", " , seq-01"):
        with pytest.raises(InputError, match="an empty name"):
            _dataset().resolve_split(empty)


def test_split_lists_through_the_command_line(tiny_map, dataset, tmp_path):
    report = tmp_path / "r.json"
    one_error_line(cli("evaluate", tiny_map, dataset, "--split", "seq-02,seq-02", "--report",
                       report, "--method", "matching"), "--split 'seq-02,seq-02'", "twice")
    one_error_line(cli("evaluate", tiny_map, dataset, "--split", "query,seq-02", "--report",
                       report, "--method", "matching"),
                   "sequence 'seq-02' twice", "in 'query'")
    line = one_error_line(cli("evaluate", tiny_map, dataset, "--split", "query,nosuch",
                              "--report", report, "--method", "matching"), "'nosuch'")
    assert "unknown split or sequence 'query'" not in line
    assert not report.exists()


# --- #12 #13: --limit -------------------------------------------------------------------------

LIMIT_TEXT = st.one_of(
    st.integers(-10, 10 ** 12).map(str),
    st.sampled_from(["1e3", "1000.0", "1_000", " 1000", "1000 ", "+7", "0x10", "١٠", "nan",
                     "inf", "", "-0", "5e7", "00012"]),
    st.text(alphabet="0123456789e.+-_ ", max_size=8))


@FAST
@given(text=LIMIT_TEXT, name=st.sampled_from(LIMIT_NAMES))
def test_a_limit_is_a_positive_whole_number_by_the_number_rule(text, name):
    whole = number_problem(text, integer=True) is None
    top = LIMIT_MAXIMA.get(name, (MAX_LIMIT,))[0]  # a bound the parser caps lower (json depth)
    if whole and 0 < int(text) <= top:
        assert parse_limits([f"{name}={text}"]) == {name: int(text)}
    else:
        with pytest.raises(InputError, match=f"^`limit` '{name}="):
            parse_limits([f"{name}={text}"])


@FAST
@given(name=st.sampled_from(LIMIT_NAMES), a=st.integers(1, 10 ** 9), b=st.integers(1, 10 ** 9),
       dashes=st.booleans())
def test_a_limit_given_twice_is_refused(name, a, b, dashes):
    """Twice, with the same value or another, and spelled with dashes or underscores."""
    again = name.replace("_", "-") if dashes else name
    top = LIMIT_MAXIMA.get(name, (MAX_LIMIT,))[0]  # within the bound's own maximum
    a, b = min(a, top), min(b, top)
    with pytest.raises(InputError, match=f"`limit` {name} is given twice"):
        parse_limits([f"{name}={a}", f"{again}={b}"])


def test_limit_errors_through_the_command_line(tiny_map, tmp_path):
    out = tmp_path / "x.tum"
    one_error_line(cli("--limit", "max_image_pixels=1e3", "export", tiny_map, "--tum", out),
                   "--limit", "'1e3' is not a whole number")
    one_error_line(cli("--limit", "max_image_pixels=10", "--limit", "max_image_pixels=99999999",
                       "export", tiny_map, "--tum", out),
                   "--limit max_image_pixels is given twice (10 and 99999999)")
    assert not out.exists()
    env = {**os.environ, "PYTHONPATH": str(REPO), "SLAMRELOC_MAX_IMAGE_PIXELS": "1e6"}
    res = subprocess.run([sys.executable, "-m", "slamreloc.cli", "export", str(tiny_map),
                          "--tum", str(out)], cwd=REPO, env=env, capture_output=True,
                         text=True, timeout=120)
    one_error_line(res, "SLAMRELOC_MAX_IMAGE_PIXELS", "not a whole number")


def test_a_small_bound_is_printed_as_it_is(tmp_path):
    """A 1000-pixel bound was "over the 0.0 MP limit"."""
    assert pixels_text(1000) == "1000 pixels" and pixels_text(16_777_216) == "16.8 MP"
    image = tmp_path / "a.png"
    cv2.imwrite(str(image), np.zeros((48, 64, 3), np.uint8))
    code = ("from slamreloc.io.limits import set_limits; from slamreloc.io.images import "
            f"read_image; set_limits(max_image_pixels=1000); read_image({str(image)!r})")
    res = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True,
                         timeout=120)
    assert "64x48 = 3072 pixels, over the 1000 pixels limit" in res.stderr, res.stderr


# --- #14: view --port ---------------------------------------------------------------------------

def _viewer_of_this_checkout() -> bool:
    code = "import slamreloc.viewer as v; print(v.__file__)"
    res = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True,
                         text=True, timeout=60)
    return res.stdout.strip().startswith(str(REPO))


@pytest.mark.parametrize("port", ["70000", "-1", "99999999999999999999"])
def test_view_and_serve_share_the_port_rule(tiny_map, port):
    if not _viewer_of_this_checkout():
        pytest.skip("slamreloc.viewer is imported from another checkout (editable install)")
    view = one_error_line(cli("view", tiny_map, "--port", port), f"--port {port}")
    serve = one_error_line(cli("serve", tiny_map, "--port", port), f"--port {port}")
    assert view.split(f"--port {port}")[1] == serve.split(f"--port {port}")[1]


def test_view_port_0_takes_a_free_port_and_prints_it(tiny_map):
    if not _viewer_of_this_checkout():
        pytest.skip("slamreloc.viewer is imported from another checkout (editable install)")
    env = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1",
           "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen([sys.executable, "-m", "slamreloc.cli", "view", str(tiny_map),
                             "--port", "0"], cwd=REPO, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        line = proc.stdout.readline()
    finally:
        proc.terminate()
        proc.communicate(timeout=60)
    assert line.startswith("viewer: http://127.0.0.1:"), line
    port = int(line.split("127.0.0.1:")[1].split()[0])
    assert 0 < port < 65536 and "busy" not in line, line


# --- #15: slam options without effect ------------------------------------------------------------

@pytest.mark.parametrize("argv, words", [
    (["--map", "MAP", "--sift-upsample"], ["--sift-upsample", "--out"]),
    (["--map", "MAP", "--out", "NEW", "--sift-upsample"], ["--sift-upsample", "--map"]),
    (["--map", "MAP", "--save-every", "5"], ["--save-every", "--out"]),
    (["--map", "MAP", "--save-every", "0"], ["--save-every", "--out"]),
    (["--map", "MAP", "--kidnap-every", "0", "--kidnap-from", "5"],
     ["--kidnap-from", "--kidnap-every"]),
    (["--map", "MAP", "--kidnap-skip", "3"], ["--kidnap-skip", "--kidnap-every"]),
    (["--map", "MAP", "--kidnap-every", "5", "--kidnap-from", "-1"],
     ["--kidnap-from", "0..10000000"]),
])
def test_a_slam_option_without_effect_is_refused(tiny_map, dataset, tmp_path, argv, words):
    names = {"MAP": tiny_map, "NEW": tmp_path / "new"}
    argv = [names.get(a, a) for a in argv]
    one_error_line(cli("slam", dataset, *argv, "--report", tmp_path / "r.json"), *words)
    assert not (tmp_path / "r.json").exists() and not (tmp_path / "new").exists()


# --- #18: export --dataset ----------------------------------------------------------------------

def _map_recording(work: Path, name: str, recorded: Path) -> Path:
    root = _tiny_map(work / name)
    meta = json.loads((root / META).read_text())
    meta["dataset"] = {"root": str(recorded.resolve()), "kind": "7scenes", "split": "train",
                       "metric": True, "poses": "dataset"}
    (root / META).write_text(json.dumps(meta))
    return root


def test_export_colours_only_from_the_maps_images(work, tiny_map, dataset, tmp_path):
    recorded_map = _map_recording(work, "recording_map", dataset)
    copy = tmp_path / "copy"
    shutil.copytree(dataset, copy)
    ply = tmp_path / "p.ply"
    # the recorded dataset, and a byte-identical copy of it: coloured
    for ds in (dataset, copy):
        res = cli("export", recorded_map, "--dataset", ds, "--ply", ply)
        assert res.returncode == 0 and "colours from the images" in res.stderr, res.stderr
        ply.unlink()
    # another dataset whose frames have the same names
    other = tmp_path / "other"
    shutil.copytree(dataset, other)
    image = other / "seq-01" / "frame-000001.color.png"
    cv2.imwrite(str(image), np.full((48, 64, 3), 77, np.uint8))
    one_error_line(cli("export", recorded_map, "--dataset", other, "--ply", ply), "--dataset",
                   str(image), "not the image of frame 'seq-01/frame-000001'")
    # a map that records no dataset: the frames' poses must be the map's
    one_error_line(cli("export", tiny_map, "--dataset", dataset, "--ply", ply), "--dataset",
                   "another pose")
    # none of the map's frames
    (other / "seq-01").rename(other / "seq-07")
    (other / "TrainSplit.txt").write_text("sequence7\n")
    (other / "scene.json").write_text(json.dumps({
        "generator": "test", "seed": 0, "depth_registered": True,
        "sequences": {"seq-07": "map", "seq-02": "query"}}))
    one_error_line(cli("export", tiny_map, "--dataset", other, "--ply", ply), "--dataset",
                   "holds none of the map's 2 frames")
    assert not ply.exists()


@pytest.mark.parametrize("argv, words", [
    (["--report", "a.json", "--report", "b.json"], ["--report is given twice"]),
    (["--report=a.json", "--report", "b.json"], ["--report is given twice"]),
    (["--report", "a.json", "--guided", "--no-guided"], ["--guided and --no-guided"]),
])
def test_an_option_taking_one_value_given_twice_is_refused(tiny_map, dataset, tmp_path, argv,
                                                            words):
    """click keeps the last of an option given twice silently: refused before any work."""
    argv = [a.replace("a.json", str(tmp_path / "a.json")) for a in argv]
    one_error_line(cli("evaluate", tiny_map, dataset, *argv), *words)
    assert not (tmp_path / "a.json").exists()


def test_view_refuses_a_json_that_is_no_report(tiny_map, tmp_path):
    """`view --report` takes evaluate, slam or pseudo-label reports; any other JSON object
    (a map's own metadata) is refused, not shown as a report."""
    if not _viewer_of_this_checkout():
        pytest.skip("slamreloc.viewer is imported from another checkout (editable install)")
    one_error_line(cli("view", tiny_map, "--report", tiny_map / META, "--port", "0"),
                   "not a report of evaluate, slam or pseudo-label")


WHOLE = "is not a whole number (whole numbers are plain ASCII digits with an optional sign"


@pytest.mark.parametrize("argv, says", [
    (["slam", "DATA", "--report", "r.json", "--kidnap-every", "1_0"],
     f"--kidnap-every: '1_0' {WHOLE}"),
    (["slam", "DATA", "--report", "r.json", "--kidnap-every= 5"], f"--kidnap-every: ' 5' {WHOLE}"),
    (["slam", "DATA", "--report", "r.json", "--kidnap-skip", "٣"], f"--kidnap-skip: '٣' {WHOLE}"),
    (["serve", "MAP", "--workers", "1e3"], f"--workers: '1e3' {WHOLE}"),
    (["serve", "MAP", "--port", "0x10"], f"--port: '0x10' {WHOLE}"),
    (["--limit", "max_image_pixels=1e3", "serve", "MAP"], f"'1e3' {WHOLE}"),
    (["localize", "MAP", "a.png", "--intrinsics", "500", "500", "3_20", "240"],
     "--intrinsics: '3_20' is not a number (numbers are plain ASCII decimals"),
])
def test_number_options_follow_the_number_rule(argv, says):
    """What int() / float() take but the number rule refuses (an exponent or a hex prefix in a
    whole number, separators, blanks, other scripts' digits) is refused in an option's value
    as in a file or a `--limit`, in the same words, before any work."""
    one_error_line(cli(*argv), says)
