"""Shared fixtures: a small synthetic scene and a quickly trained map, built once per session."""

from __future__ import annotations

import os
import shutil
import subprocess
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import pytest

from slamreloc.map.build import MapConfig
from slamreloc.regressor.train import TrainConfig
from slamreloc.synthetic import SceneConfig, render_scene

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data"
REDKITCHEN = SHARED / "7scenes_redkitchen"
STAIRS = SHARED / "7scenes_stairs_layout_sample"

# Half-resolution scene: fast to render and to map, same geometry as the demo's.
SMALL_SCENE = SceneConfig(width=320, height=240, fx=262.5, fy=262.5, cx=159.5, cy=119.5,
                          n_map=60, n_query=20, n_kidnap=30, n_unlabelled=20)
# SIFT's pyramid starts at the image's own resolution by default; on this half-size scene it
# starts at twice that (upsample), which sees the same detail as the default on the full scene.
# 60 epochs: its 20 queries all within 5 cm / 5 deg, median 0.59 cm, in 215 s on an AVX2-only
# 2-core CPU (120 epochs: median 0.50 cm in 400 s, the suite's largest single cost).
SMALL_MAP = MapConfig(arch="wide", feature_options={"upsample": True},
                      train=TrainConfig(epochs=60))


def sigint_as_from_a_terminal() -> None:
    """Popen preexec_fn: the child takes SIGINT (Ctrl-C) with the default action. A shell that
    runs the suite as a background job hands its children SIGINT ignored, and Python then
    never raises KeyboardInterrupt: the tests that press Ctrl-C must not depend on how the
    suite was started."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_DFL)


def needs(path: Path):
    return pytest.mark.skipif(not path.is_dir(), reason=f"real data not found at {path}")


def built_once(tmp_path_factory, key: str, leaf: str, build: Callable[[Path], object]) -> Path:
    """The folder `leaf` (under a temporary folder `key`) that `build(folder)` fills, built
    once per test run: by this process alone, or under pytest-xdist by the first worker that
    needs it (the others wait on its lock, then read the same folder). The tests only read it."""
    worker = os.environ.get("PYTEST_XDIST_WORKER")
    if worker is None:
        folder = tmp_path_factory.mktemp(key) / leaf
        build(folder)
        return folder
    from filelock import FileLock

    shared = tmp_path_factory.getbasetemp().parent  # the run's root, above each worker's
    folder, done = shared / key / leaf, shared / f"{key}.done"
    with FileLock(str(shared / f"{key}.lock")):
        if not done.exists():
            shutil.rmtree(folder.parent, ignore_errors=True)
            folder.parent.mkdir()
            build(folder)
            done.touch()
    return folder


@pytest.fixture(scope="session")
def scene_dir(tmp_path_factory) -> Path:
    return built_once(tmp_path_factory, "synthetic", "scene",
                      lambda out: render_scene(out, SMALL_SCENE))


@pytest.fixture(scope="session")
def small_map(scene_dir, tmp_path_factory):
    from slamreloc.datasets import load_dataset
    from slamreloc.map.build import build_map
    from slamreloc.map.scene_map import SceneMap

    folder = built_once(tmp_path_factory, "maps", "small_map", lambda out: build_map(
        load_dataset(scene_dir), out, "train", SMALL_MAP, progress=False))
    return SceneMap.load(folder)


def small_map_config(**train) -> MapConfig:
    return replace(SMALL_MAP, train=replace(SMALL_MAP.train, **train))


def pytest_configure(config):
    """Under pytest-xdist, each worker (and each command it starts) takes its share of the
    cores: two workers of two threads on two cores made every test that trains or extracts
    take turns with the other worker's, no faster in all than one process."""
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "0"))
    if workers > 1:
        import torch

        share = str(max(1, (os.cpu_count() or 1) // workers))
        os.environ["OMP_NUM_THREADS"] = share
        torch.set_num_threads(int(share))


def _fuzz_counts_folder(config) -> Path:
    """Where each pytest-xdist worker leaves its fuzz counts for the terminal summary."""
    root = config._tmp_path_factory.getbasetemp()  # the session's (the workers' lie inside)
    return (root.parent if os.environ.get("PYTEST_XDIST_WORKER") else root) / "fuzz_counts"


def pytest_sessionfinish(session, exitstatus):
    """A pytest-xdist worker writes what tests/fuzzing.py counted, for the summary."""
    import json
    import sys

    worker = os.environ.get("PYTEST_XDIST_WORKER")
    fuzzing = sys.modules.get("tests.fuzzing")
    if worker is None or fuzzing is None:
        return
    folder = _fuzz_counts_folder(session.config)
    folder.mkdir(exist_ok=True)
    (folder / f"{worker}.json").write_text(json.dumps({
        "kills": fuzzing.KILL_REPORTS,
        "counts": [[fmt, outcome, n] for (fmt, outcome), n in fuzzing.COUNTS.items()]}))


def pytest_terminal_summary(terminalreporter, exitstatus, config):
    """Print how many fuzz cases ran (tests/fuzzing.py counts them), when any did: this
    process's, or under pytest-xdist its workers' together."""
    import json
    import sys

    fuzzing = sys.modules.get("tests.fuzzing")
    folder = _fuzz_counts_folder(config)
    if folder.is_dir():  # the workers' (xdist): into this process's tallies
        import tests.fuzzing as fuzzing

        for part in sorted(folder.glob("gw*.json")):
            data = json.loads(part.read_text())
            fuzzing.KILL_REPORTS.extend(data["kills"])
            for fmt, outcome, n in data["counts"]:
                fuzzing.COUNTS[fmt, outcome] += n
    if fuzzing is None:
        return
    for r in fuzzing.KILL_REPORTS:
        terminalreporter.write_sep("-", f"kill -9 harness: {r['kills']} kills of "
                                        f"`{r['command']}` in {r['total_s']} s")
        terminalreporter.write_line("  " + ", ".join(f"{k} {v}" for k, v in r.items()
                                                     if k not in ("command", "failures")))
    if not fuzzing.total_cases():
        return
    s = fuzzing.summary()
    terminalreporter.write_sep("-", f"fuzzing: {s['total']} generated bad-input cases")
    for fmt, outcomes in s["by_format"].items():
        terminalreporter.write_line(f"  {fmt}: " + ", ".join(f"{k} {v}" for k, v in
                                                             outcomes.items()))


@pytest.fixture(scope="session")
def client_binary(tmp_path_factory) -> Path:
    """clients/cpp built once per test run into a temporary folder (no optimisation: the build
    is what costs); the modules that use it skip first where the tools are missing."""
    root = Path(__file__).resolve().parents[1]

    def build(folder: Path) -> None:
        t0 = time.perf_counter()
        for cmd in (["cmake", "-S", str(root / "clients/cpp"), "-B", str(folder)],
                    ["cmake", "--build", str(folder), "-j", "2"]):
            done = subprocess.run(cmd, capture_output=True, text=True, timeout=600, check=False)
            assert done.returncode == 0, f"{' '.join(cmd)}:\n{done.stdout[-3000:]}{done.stderr}"
        print(f"clients/cpp built in {time.perf_counter() - t0:.1f} s")

    return built_once(tmp_path_factory, "cpp", "build", build) / "slamreloc_client"


@pytest.fixture(scope="session")
def viewer_case(scene_dir, tmp_path_factory):
    """A synthetic map folder with trajectories and reports for the viewer's tests (built once
    for both viewer test modules)."""
    from tests.viewer_support import build_case

    return build_case(scene_dir, tmp_path_factory.mktemp("viewer"))


@pytest.fixture(scope="session")
def kidnap_scene(tmp_path_factory):
    """The small scene's room with a 120-frame kidnap sequence (the fixture scene has 30);
    used by the SLAM tests of both modules, rendered once."""
    config = replace(SMALL_SCENE, n_map=2, n_query=2, n_kidnap=120, n_unlabelled=2)
    return built_once(tmp_path_factory, "kidnap", "scene", lambda out: render_scene(out, config))
