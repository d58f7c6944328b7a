"""The reported cases, through the real command line (`python -m slamreloc.cli evaluate`):
each ends in exit status 2 with one `error: <file>: <problem>` line, never a traceback.

The same checks run on thousands of generated cases in tests/test_fuzz_inputs.py (in process);
these few pay for a real interpreter start each.
"""

from __future__ import annotations

import json
import os
import pickle
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from slamreloc.map.format import DATABASE, LEGACY_WEIGHTS, META, WEIGHTS
from tests.test_fuzz_inputs import _tiny_map, make_sevenscenes
from tests.test_map_format import Payload

REPO = Path(__file__).resolve().parents[1]


def _random_bytes(root, ds, tmp):
    (root / WEIGHTS).write_bytes(np.random.default_rng(0).bytes(20000))
    return root / WEIGHTS


def _flipped_bits(root, ds, tmp):
    data = bytearray((root / WEIGHTS).read_bytes())
    for pos in (200, 900, 1500):
        data[pos] ^= 0x10
    (root / WEIGHTS).write_bytes(bytes(data))
    return root / WEIGHTS


def _pickle_payload_pt(root, ds, tmp):
    """A format-1 map whose regressor.pt would create a file if unpickled."""
    meta = json.loads((root / META).read_text())
    meta = {k: v for k, v in meta.items() if k not in ("format_version", "files")}
    (root / META).write_text(json.dumps({**meta, "version": 1}))
    (root / WEIGHTS).unlink()
    torch.save({"mlp.0.weight": Payload(tmp / "payload-ran")}, root / LEGACY_WEIGHTS)
    return root / LEGACY_WEIGHTS


def _pickle_payload_npz(root, ds, tmp):
    np.savez(root / DATABASE, descriptors=np.array([Payload(tmp / "payload-ran")], object))
    return root / DATABASE


def _json_list(root, ds, tmp):
    (root / META).write_text("[1, 2]")
    return root / META


def _future_version(root, ds, tmp):
    meta = json.loads((root / META).read_text())
    (root / META).write_text(json.dumps({**meta, "format_version": 999}))
    return root / META


def _split_names_missing_sequence(root, ds, tmp):
    (ds / "TestSplit.txt").write_text("sequence2\nsequence7\n")
    return ds / "TestSplit.txt"


def _empty_query_sequence(root, ds, tmp):
    for p in (ds / "seq-02").iterdir():
        p.unlink()
    return ds / "TestSplit.txt"


def _truncated_jpeg(root, ds, tmp):
    path = ds / "seq-02" / "frame-000001.color.jpg"
    path.write_bytes(path.read_bytes()[:400])
    return path


CASES = [_random_bytes, _flipped_bits, _pickle_payload_pt, _pickle_payload_npz, _json_list,
         _future_version, _split_names_missing_sequence, _empty_query_sequence, _truncated_jpeg]


@pytest.fixture(scope="module")
def outcomes(tmp_path_factory):
    """Every case run as its own `python -m slamreloc.cli evaluate`, two at a time."""
    work = tmp_path_factory.mktemp("cli")
    base_map = _tiny_map(work / "base" / "map")
    base_ds = make_sevenscenes(work / "base" / "ds")
    env = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"}
    runs = {}
    for case in CASES:
        tmp = work / case.__name__
        root, ds = tmp / "map", tmp / "ds"
        shutil.copytree(base_map, root)
        shutil.copytree(base_ds, ds)
        bad = case(root, ds, tmp)
        cmd = [sys.executable, "-m", "slamreloc.cli", "evaluate", str(root), str(ds),
               "--report", str(tmp / "r.json"), "--method", "matching"]
        runs[case.__name__] = (bad, tmp, cmd)
    results, running = {}, []
    for name, (bad, tmp, cmd) in runs.items():
        running.append((name, bad, tmp, subprocess.Popen(
            cmd, cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)))
        if len(running) == 2 or name == list(runs)[-1]:
            for n, b, t, proc in running:
                _, err = proc.communicate(timeout=300)
                results[n] = (proc.returncode, err, b, t)
            running = []
    return results


@pytest.mark.parametrize("case", [c.__name__ for c in CASES])
def test_bad_input_is_one_line_and_exit_2(outcomes, case):
    code, stderr, bad, tmp = outcomes[case]
    assert "Traceback" not in stderr, stderr
    assert code == 2, stderr
    lines = [ln for ln in stderr.splitlines() if ln.strip()]
    assert lines[-1].startswith(f"error: {bad}: "), lines[-1]
    assert sum(ln.startswith("error:") for ln in lines) == 1
    assert not (tmp / "payload-ran").exists()
    assert not (tmp / "r.json").exists()  # no report as if all were well


def test_the_payloads_are_real(tmp_path):
    """The pickle payloads used above do run when unpickled unsafely."""
    pickle.loads(pickle.dumps(Payload(tmp_path / "ran")))
    assert (tmp_path / "ran").exists()


@pytest.mark.parametrize("argv, flags", [
    (["sfm", "IN", "--out", "OUT", "--scale", "2", "--scale-from-depth"],
     ["--scale and --scale-from-depth: give one of them"]),
    (["serve", "MAP", "--host", "0.0.0.0"],
     ["--host 0.0.0.0 is not a loopback address", "--token-file", "--tls-cert/--tls-key"]),
    # numbers that are no number or out of range are refused, never taken as "off"
    (["serve", "MAP", "--max-request-mb", "nan"], ["--max-request-mb nan: 0.0625 to 2047"]),
    (["serve", "MAP", "--watch", "nan"], ["--watch nan: seconds between checks"]),
    (["serve", "MAP", "--watch", "-1"], ["--watch -1.0: seconds between checks"]),
])
def test_a_library_error_names_the_flag(tmp_path, argv, flags):
    """The library names a setting `field` (SfmConfig, ServeConfig); the command line's error
    line names its flag, with no backtick left."""
    argv = [str(tmp_path / a) if a.isupper() else a for a in argv]
    env = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"}
    res = subprocess.run([sys.executable, "-m", "slamreloc.cli", *argv], cwd=REPO, env=env,
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 2 and "Traceback" not in res.stderr, res.stderr
    (line,) = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert line.startswith("error: ") and "`" not in line, line
    for text in flags:
        assert text in line, line


def test_the_same_errors_name_the_fields_in_python():
    from slamreloc.errors import InputError
    from slamreloc.service.server import ServeConfig
    from slamreloc.sfm import SfmConfig

    with pytest.raises(InputError, match="^`scale` and `scale_from_depth`: give one of them$"):
        SfmConfig(scale=2.0, scale_from_depth=True)
    with pytest.raises(InputError, match=r"^`port` 70000: not a TCP port \(0 for any free "
                                         r"one, or 1 to 65535\)$"):
        ServeConfig(port=70000).check()
    with pytest.raises(InputError, match="^`watch_s` nan: seconds between checks"):
        ServeConfig(watch_s=float("nan")).check()


def test_demo_workdir_under_a_file_is_one_line(tmp_path):
    """`demo --workdir` under a regular file: one line naming the option and the file, before
    any stage runs (was "[Errno 17] File exists")."""
    (tmp_path / "notes.txt").write_text("mine")
    env = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"}
    res = subprocess.run([sys.executable, "-m", "slamreloc.cli", "demo", "--no-viewer",
                          "--workdir", str(tmp_path / "notes.txt" / "demo")], cwd=REPO, env=env,
                         capture_output=True, text=True, timeout=120)
    (line,) = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert res.returncode == 2 and "--workdir" in line and "is a file" in line, res.stderr
    assert (tmp_path / "notes.txt").read_text() == "mine"
