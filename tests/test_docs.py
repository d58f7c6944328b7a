"""The documentation runs as written: every fenced code block of README.md and docs/*.md (one
test per block, `docs/serve.md:42`), and every relative link and Python name the pages
mention resolves.

How a block runs is told by its language and by an optional annotation on the line directly
above it, invisible to readers: `<!-- docs-test: WORD ... needs=INPUT,... -->`.
- `bash` / `sh` / `shell` blocks run with `bash -e -o pipefail`, `python` blocks with the
  suite's interpreter, in a fresh folder; anything else needs an annotation that says how it
  is checked (docs_support.TAGS), and a block the test does not know how to run fails, so a
  new block cannot go untested by accident.
- `needs=` names the inputs the test creates there first, through the project's own code:
  `slamreloc-demo` (what `slamreloc demo` writes: the suite's synthetic scene and map from
  tests/conftest.py, and an `evaluate` run on its query sequence), `server:NAME` (that map
  served under NAME on 127.0.0.1:50051), stand-ins for a user's files (`walk.mp4`, `photos`,
  `recording`, `query.jpg`, `run.bag`, `run2.bag`, `token.txt`, rendered from the synthetic
  scene) and real-data inputs (`maps/redkitchen`, `orb.txt`).
- `server`: the block starts a server that runs until Ctrl-C. It is started, must print its
  address and answer there (gRPC Health, or the viewer's page), and is stopped with SIGINT.
- `realdata` blocks read ../shared/data and take minutes: they run only with
  SLAMRELOC_DOCS_REALDATA=1 (and skip without the data), all in one folder beside a link to
  ../shared, in page order, so that later blocks find what earlier ones wrote (the README's
  first run makes `maps/redkitchen`, about 5 min of mapping on 2 cores).
- `slow` blocks take minutes on the synthetic scene (SfM, a map trained with the default
  epochs, Ray): they run only with SLAMRELOC_DOCS_SLOW=1, in one folder, in page order.
- `make-dry-run` (`make demo`, `make test`: an install, and the suite itself) checks each
  target with `make -n`; `pyproject` checks a TOML excerpt against pyproject.toml and loads its
  entry points; `output`, `network` and `cluster` blocks are skipped with their reason.
"""

from __future__ import annotations

import importlib
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
import urllib.request
from dataclasses import replace
from pathlib import Path

import pytest

from tests.conftest import SHARED, SMALL_SCENE, sigint_as_from_a_terminal
from tests.docs_support import (
    BLOCK_PAGES,
    DOTTED,
    LINK_PAGES,
    ROOT,
    SCRIPT_RUN,
    SOURCE_PATH,
    TAGS,
    Block,
    all_blocks,
    anchors,
    relative_links,
    script_file,
)

BLOCKS = all_blocks()
REALDATA = os.environ.get("SLAMRELOC_DOCS_REALDATA") == "1"
SLOW = os.environ.get("SLAMRELOC_DOCS_SLOW") == "1"
SHELLS = {"bash", "sh", "shell"}
PYTHONS = {"python", "py", "python3"}
SERVICE_PORT = 50051  # the documented default of `slamreloc serve` and `Client()`
TOKEN = "docs-test-token-0123456789"
# per block, generous for a loaded 2-core machine; real data maps RedKitchen (~5 min)
TIMEOUT_S = {"default": 600, "slow": 1800, "realdata": 3600}


# ----------------------------------------------------------------------------- inputs


@pytest.fixture(scope="session")
def demo_outputs(request, tmp_path_factory) -> Path:
    """What `make demo` leaves that the pages read, made once by the command the demo runs:
    `slamreloc evaluate` of the suite's small map on its scene's query sequence (report.json,
    poses_regressor.txt and its names)."""
    scene, small_map = request.getfixturevalue("scene_dir"), request.getfixturevalue("small_map")
    out = tmp_path_factory.mktemp("docs-demo")
    _run(["slamreloc", "evaluate", str(small_map.root), str(scene), "--split", "query",
          "--report", "report.json", "--trajectory", "poses_regressor.txt"], out,
         TIMEOUT_S["default"], "slamreloc evaluate for slamreloc-demo/")
    return out


def _make_demo_folder(work: Path, request) -> None:
    demo = work / "slamreloc-demo"
    if demo.exists():
        return
    demo.mkdir()
    (demo / "scene").symlink_to(request.getfixturevalue("scene_dir"))
    (demo / "map").symlink_to(request.getfixturevalue("small_map").root)
    for f in request.getfixturevalue("demo_outputs").iterdir():
        shutil.copyfile(f, demo / f.name)


def _scene(request):
    from slamreloc.datasets import load_dataset

    return load_dataset(request.getfixturevalue("scene_dir"))


def _walk_video(work: Path, request) -> None:
    import cv2

    from slamreloc.io.images import read_image

    frames = _scene(request).frames("map")
    h, w = frames[0].camera.height, frames[0].camera.width
    # 4 frames per second of video: `--fps 2` keeps every other one
    writer = cv2.VideoWriter(str(work / "walk.mp4"), cv2.VideoWriter_fourcc(*"mp4v"), 4.0, (w, h))
    for f in frames:
        writer.write(read_image(f.image_path)[:, :, ::-1])
    writer.release()


def _photos(work: Path, request) -> None:
    (work / "photos").mkdir()
    for f in _scene(request).frames("map")[:40]:
        shutil.copyfile(f.image_path, work / "photos" / f"{f.name.split('/')[-1]}.png")


def _recording(work: Path, request) -> None:
    from slamreloc.synthetic import render_scene

    render_scene(work / "recording", replace(SMALL_SCENE, n_map=40, n_query=2, n_kidnap=2,
                                             n_unlabelled=2))


def _query_jpg(work: Path, request) -> None:
    import cv2

    frame = _scene(request).frames("query")[0]
    cv2.imwrite(str(work / "query.jpg"), cv2.imread(str(frame.image_path)))


def _bag(name: str, role: str):
    """A ROS 1 bag of 30 frames of a sequence: raw images on /cam/color/image_raw, registered
    depth, CameraInfo, the robot's odometry on /odom and the rig on /tf_static."""
    def make(work: Path, request) -> None:
        from tests.rosbag_support import write_bag

        dataset = _scene(request)
        write_bag(dataset, dataset.frames(role)[:30], work / name, version=1, compressed=False,
                  poses="odometry")
    return make


def _token(work: Path, request) -> None:
    (work / "token.txt").write_text(TOKEN + "\n")


def _redkitchen_map(work: Path, request) -> None:
    if not (work / "maps" / "redkitchen").is_dir():
        _run(["slamreloc", "map", "../shared/data/7scenes_redkitchen", "--out",
              "maps/redkitchen"], work, TIMEOUT_S["realdata"], "making maps/redkitchen")


def _orb_txt(work: Path, request) -> None:
    """A stand-in for another SLAM system's trajectory: the test split's poses as TUM."""
    from slamreloc.datasets import load_dataset
    from slamreloc.geometry import write_tum_trajectory

    frames = load_dataset(SHARED / "7scenes_redkitchen").frames("test")
    write_tum_trajectory(work / "orb.txt", [f.timestamp for f in frames],
                         [f.world_from_cam for f in frames])


PRODUCERS = {
    "slamreloc-demo": _make_demo_folder,
    "walk.mp4": _walk_video,
    "photos": _photos,
    "recording": _recording,
    "query.jpg": _query_jpg,
    "run.bag": _bag("run.bag", "map"),
    "run2.bag": _bag("run2.bag", "kidnap"),
    "token.txt": _token,
    "maps/redkitchen": _redkitchen_map,
    "orb.txt": _orb_txt,
}


def _port_free(port: int, wait_s: float = 30.0) -> bool:
    """Whether a server may bind `port` (as gRPC does, with SO_REUSEADDR: a server stopped a
    moment ago leaves its port in TIME_WAIT), waiting a while for one that is still closing."""
    deadline = time.monotonic() + wait_s
    while True:
        with socket.socket() as s:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                s.bind(("127.0.0.1", port))
                return True
            except OSError:
                if time.monotonic() > deadline:
                    return False
        time.sleep(0.5)


# ----------------------------------------------------------------------------- running


def _env() -> dict[str, str]:
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    env["PATH"] = os.pathsep.join([str(Path(sys.executable).parent), env.get("PATH", "")])
    return env


def _run(cmd: list[str], cwd: Path, timeout: float, what: str) -> None:
    try:
        done = subprocess.run(cmd, cwd=cwd, env=_env(), capture_output=True, text=True,
                              timeout=timeout, preexec_fn=sigint_as_from_a_terminal)
    except subprocess.TimeoutExpired as err:
        pytest.fail(f"{what}: still running after {timeout:.0f} s\n{_tail(err.stdout, err.stderr)}")
    if done.returncode != 0:
        pytest.fail(f"{what}: exit status {done.returncode}\n{_tail(done.stdout, done.stderr)}")


def _tail(stdout, stderr, n: int = 4000) -> str:
    def text(s):
        return s.decode(errors="replace") if isinstance(s, bytes) else (s or "")
    return f"--- stdout\n{text(stdout)[-n:]}\n--- stderr\n{text(stderr)[-n:]}"


def _script(block: Block, work: Path) -> list[str]:
    if block.lang in SHELLS:
        path = work / f"_block_{block.line}.sh"
        path.write_text(block.code)
        return ["bash", "-e", "-o", "pipefail", str(path)]
    path = work / f"_block_{block.line}.py"
    path.write_text(block.code)
    return [sys.executable, str(path)]


def _answers(address: str, work: Path) -> str | None:
    """None when the server at `address` answers, else what went wrong."""
    try:
        if address.startswith("http"):
            with urllib.request.urlopen(address, timeout=30) as response:
                return None if response.status == 200 else f"HTTP {response.status}"
        from slamreloc.client import Client

        token = (work / "token.txt").read_text().strip() if (work / "token.txt").exists() \
            else None
        with Client(address, token=token, timeout_s=60) as client:
            return None if client.health().serving else "Health says it is not serving"
    except Exception as err:  # noqa: BLE001 - reported as the failure
        return f"{type(err).__name__}: {err}"


def _run_server(block: Block, work: Path, timeout: float) -> None:
    proc = subprocess.Popen(_script(block, work), cwd=work, env=_env(), text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            start_new_session=True, preexec_fn=sigint_as_from_a_terminal)
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(iter(proc.stdout.readline, "")),
                              daemon=True)
    reader.start()
    pattern = re.compile(r"listening on (\S+)|(http://\S+)")
    address, problem = None, None
    try:
        deadline = time.monotonic() + timeout
        while address is None and proc.poll() is None and time.monotonic() < deadline:
            for line in list(lines):
                m = pattern.search(line)
                if m:
                    address = m.group(1) or m.group(2)
                    break
            time.sleep(0.2)
        if address is None:
            problem = ("exited before printing its address" if proc.poll() is not None
                       else f"printed no address within {timeout:.0f} s")
        else:
            problem = _answers(address, work)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGINT)  # Ctrl-C, to the whole block
            try:
                proc.wait(60)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
                problem = problem or "did not stop within 60 s of Ctrl-C"
        reader.join(5)
    if problem is None and proc.returncode not in (0, 130, -signal.SIGINT):
        problem = f"ended with exit status {proc.returncode} after Ctrl-C"
    if problem:
        pytest.fail(f"server block {block.id}: {problem}\n" + "".join(lines)[-4000:])


def _check_make(block: Block) -> None:
    for line in block.code.splitlines():
        command = line.split("#", 1)[0].split()
        if not command:
            continue
        assert command[0] == "make", f"{block.id}: a make-dry-run block holds make commands only"
        _run(["make", "-n", *command[1:]], ROOT, 60, f"make -n {' '.join(command[1:])}")


def _check_pyproject(block: Block) -> None:
    import tomllib

    excerpt = tomllib.loads(block.code)
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())

    def within(part, whole, where):
        for key, value in part.items():
            assert key in whole, f"{block.id}: {where}{key} is not in pyproject.toml"
            if isinstance(value, dict):
                within(value, whole[key], f"{where}{key}.")
            else:
                assert whole[key] == value, f"{block.id}: {where}{key} differs from pyproject.toml"
    within(excerpt, project, "")
    for group in excerpt.get("project", {}).get("entry-points", {}).values():
        for target in group.values():
            module, _, attr = target.partition(":")
            assert getattr(importlib.import_module(module), attr)


@pytest.fixture(scope="session")
def shared_folder(tmp_path_factory):
    """Per tier (realdata, slow): one folder for all its blocks, beside a link to ../shared."""
    made: dict[str, Path] = {}

    def folder(tier: str) -> Path:
        if tier not in made:
            base = tmp_path_factory.mktemp(f"docs-{tier}")
            (base / "shared").symlink_to(SHARED.parent)
            (base / "checkout").mkdir()
            made[tier] = base / "checkout"
        return made[tier]
    return folder


@pytest.mark.parametrize("block", BLOCKS, ids=[b.id for b in BLOCKS])
def test_block_runs_as_written(block: Block, request, tmp_path, shared_folder):
    assert not block.problems, f"{block.id}: " + "; ".join(block.problems)
    for skip in ("output", "network", "cluster"):
        if skip in block.tags:
            pytest.skip(f"{block.id}: {TAGS[skip]}")
    if "make-dry-run" in block.tags:
        return _check_make(block)
    if "pyproject" in block.tags:
        return _check_pyproject(block)
    if block.lang not in SHELLS | PYTHONS:
        pytest.fail(f"{block.id}: the test does not know how to run a '{block.lang or 'plain'}'"
                    f" block; annotate it (<!-- docs-test: ... -->, see tests/test_docs.py)")
    if "../shared/data" in block.code and "realdata" not in block.tags:
        pytest.fail(f"{block.id}: the block reads ../shared/data: annotate it `realdata`")
    tier = "default"
    if "realdata" in block.tags:
        tier = "realdata"
        if not REALDATA:
            pytest.skip("real-data block (minutes of CPU): set SLAMRELOC_DOCS_REALDATA=1")
        if not (SHARED / "7scenes_redkitchen").is_dir():
            pytest.skip(f"real data not found at {SHARED}")
    elif "slow" in block.tags:
        tier = "slow"
        if not SLOW:
            pytest.skip("slow block (minutes of CPU): set SLAMRELOC_DOCS_SLOW=1")
    work = tmp_path if tier == "default" else shared_folder(tier)

    servers = []
    try:
        for need in block.needs:
            if need.startswith("server:"):
                if not _port_free(SERVICE_PORT):
                    pytest.skip(f"port {SERVICE_PORT}, which the block calls, is in use")
                from slamreloc.service.server import ServeConfig, start_server

                servers.append(start_server(
                    {need.split(":", 1)[1]: request.getfixturevalue("small_map").root},
                    ServeConfig(port=SERVICE_PORT, watch_s=0)))
            elif need in PRODUCERS:
                if not (work / need).exists() or need == "slamreloc-demo":
                    PRODUCERS[need](work, request)
            else:
                pytest.fail(f"{block.id}: needs '{need}', which the test cannot make "
                            f"(known: {', '.join(sorted(PRODUCERS))}, server:NAME)")
        if "server" in block.tags:
            if "slamreloc serve" in block.code and "--port" not in block.code \
                    and not _port_free(SERVICE_PORT):
                pytest.skip(f"port {SERVICE_PORT}, which the block binds, is in use")
            _run_server(block, work, TIMEOUT_S[tier])
        else:
            _run(_script(block, work), work, TIMEOUT_S[tier], f"block {block.id}")
    finally:
        for server in servers:
            server.stop()


# ----------------------------------------------------------------------------- references


def test_every_page_is_read():
    assert {p.name for p in BLOCK_PAGES} >= {"README.md", "method.md", "formats.md", "slam.md",
                                             "serve.md", "own-data.md", "map-updates.md",
                                             "viewer.md", "python-api.md", "history.md"}
    assert any(b.lang in PYTHONS for b in BLOCKS) and any(b.lang in SHELLS for b in BLOCKS)


@pytest.mark.parametrize("page", LINK_PAGES, ids=[p.relative_to(ROOT).as_posix()
                                                   for p in LINK_PAGES])
def test_relative_links_resolve(page: Path):
    broken = []
    for line, target in relative_links(page):
        path, _, anchor = target.partition("#")
        dest = (page.parent / path).resolve() if path else page
        if not dest.exists():
            broken.append(f"{page.name}:{line}: {target}: no such file")
        elif anchor and dest.suffix == ".md" and anchor not in anchors(dest):
            broken.append(f"{page.name}:{line}: {target}: no such heading in {dest.name}")
    assert not broken, "\n".join(broken)


def _resolves(name: str) -> bool:
    parts = name.split(".")
    for i in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:i]))
        except ImportError:
            continue
        try:
            for attr in parts[i:]:
                obj = getattr(obj, attr)
        except AttributeError:
            return False
        return True
    return False


# the pages that describe today's code (docs/history.md is a record of earlier code)
CURRENT_PAGES = [p for p in LINK_PAGES if p.name != "history.md"]


@pytest.mark.parametrize("page", CURRENT_PAGES, ids=[p.relative_to(ROOT).as_posix()
                                                      for p in CURRENT_PAGES])
def test_named_modules_and_files_exist(page: Path):
    text = page.read_text()
    missing = [n for n in sorted(set(DOTTED.findall(text)))
               if n != "slamreloc.v1" and not _resolves(n)]  # slamreloc.v1: the protocol
    missing += [p for p in sorted(set(SOURCE_PATH.findall(text)))
                if not (ROOT / p.rstrip("/")).exists()]
    missing += [s for s in sorted(set(SCRIPT_RUN.findall(text))) if not script_file(s).is_file()]
    assert not missing, f"{page.name} names what does not exist: {missing}"


def test_front_door_stays_short():
    """A reference, not a log: the README and BENCHMARKS.md within their bounds (history goes
    to docs/history.md)."""
    assert len((ROOT / "README.md").read_text().splitlines()) <= 150
    assert len((ROOT / "BENCHMARKS.md").read_text().splitlines()) <= 400
