"""Shared fixtures: a small synthetic scene and a quickly trained map, built once per session."""

from __future__ import annotations

import subprocess
import time
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


@pytest.fixture(scope="session")
def scene_dir(tmp_path_factory) -> Path:
    return render_scene(tmp_path_factory.mktemp("synthetic") / "scene", SMALL_SCENE)


@pytest.fixture(scope="session")
def small_map(scene_dir, tmp_path_factory):
    from slamreloc.datasets import load_dataset
    from slamreloc.map.build import build_map

    out = tmp_path_factory.mktemp("maps") / "small_map"
    return build_map(load_dataset(scene_dir), out, "train", SMALL_MAP, progress=False)


def small_map_config(**train) -> MapConfig:
    return replace(SMALL_MAP, train=replace(SMALL_MAP.train, **train))


def pytest_terminal_summary(terminalreporter, exitstatus, config):
    """Print how many fuzz cases ran (tests/fuzzing.py counts them), when any did."""
    import sys

    fuzzing = sys.modules.get("tests.fuzzing")
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
    build = tmp_path_factory.mktemp("cpp_build")
    t0 = time.perf_counter()
    for cmd in (["cmake", "-S", str(root / "clients/cpp"), "-B", str(build)],
                ["cmake", "--build", str(build), "-j", "2"]):
        done = subprocess.run(cmd, capture_output=True, text=True, timeout=600, check=False)
        assert done.returncode == 0, f"{' '.join(cmd)}:\n{done.stdout[-3000:]}{done.stderr}"
    print(f"clients/cpp built in {time.perf_counter() - t0:.1f} s")
    return build / "slamreloc_client"


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
    return render_scene(tmp_path_factory.mktemp("kidnap") / "scene", config)
