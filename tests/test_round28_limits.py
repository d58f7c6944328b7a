"""Attack round 28, J3 and J4: the input bounds (`slamreloc.io.limits`) as they are set.

J3: `slamreloc --limit ... serve --engine ray` held the bounds in the driver only; the Ray Serve
map replicas read their own environment (a Localize over the bound was answered). The replicas
now take the driver's `limits()` (the end-to-end check through Serve's gRPC proxy is in
tests/test_ray_serve.py, on its one Ray instance).

J4: `SLAMRELOC_max_image_pixels`, `SLAMRELOC_MAXIMAGE_PIXELS`, ... were ignored (the command ran
with the default bound): a SLAMRELOC_ name in any case that names no setting, or a name spelt
like a setting but for case and punctuation, is refused in one line naming it.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from dataclasses import asdict, fields, replace
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from slamreloc.errors import InputError
from slamreloc.io import limits as limits_module
from slamreloc.io.limits import (
    BOUND_VARIABLES,
    KNOWN_VARIABLES,
    InputLimits,
    check_environment,
    environment_problem,
    limits,
)
from tests.fuzzing import run_cli
from tests.test_fuzz_inputs import _tiny_map

REPO = Path(__file__).resolve().parents[1]
BOUNDS = [f.name for f in fields(InputLimits)]
# the report's three spellings, each taken with the default bound before
REPORTED = ["SLAMRELOC_max_image_pixels", "SLAMRELOC_Max_Image_Pixels",
            "SLAMRELOC_MAXIMAGE_PIXELS"]


def resembles_bound(name: str, bound: str) -> str:
    return (f"environment variable {name} names no bound: it resembles the bound {bound}, "
            f"whose variable is exactly SLAMRELOC_{bound.upper()}")


@pytest.fixture(scope="module")
def tiny_map(tmp_path_factory) -> Path:
    return _tiny_map(tmp_path_factory.mktemp("round28") / "map")


@pytest.fixture()
def fresh_limits(monkeypatch):
    """The bounds as a new process starts with them (read from the environment at first use);
    this process's own bounds are put back afterwards."""
    monkeypatch.setattr(limits_module, "_current", None)


def png(width: int, height: int) -> bytes:
    rng = np.random.default_rng(width * height)
    return cv2.imencode(".png", rng.integers(0, 255, (height, width, 3), np.uint8))[1].tobytes()


# ---- J4: SLAMRELOC_ names read exactly ---------------------------------------------------------
@pytest.mark.parametrize("name", REPORTED + ["SLAMRELOC_MAX_IMAGE_PIXEL"])
def test_a_misspelt_bound_variable_ends_the_command_naming_the_bound(name, monkeypatch,
                                                                    tmp_path):
    """J4: the report's spellings ran `localize` under the default bound, rc 0."""
    image = tmp_path / "x.png"
    image.write_bytes(png(64, 48))
    monkeypatch.setenv(name, "1000")
    code, err = run_cli(["localize", str(tmp_path / "no-map"), str(image)])
    assert code == 2, err
    assert err.strip().splitlines() == [f"error: {resembles_bound(name, 'max_image_pixels')}"]


def test_the_exact_bound_variable_still_holds(tiny_map, tmp_path, monkeypatch, fresh_limits):
    """The other side of J4: SLAMRELOC_MAX_IMAGE_PIXELS, as spelt in the docs, is taken."""
    image = tmp_path / "x.png"
    image.write_bytes(png(64, 48))
    monkeypatch.setenv("SLAMRELOC_MAX_IMAGE_PIXELS", "1000")
    code, err = run_cli(["localize", str(tiny_map), str(image)])
    assert code == 2 and "3072 pixels, over the 1000 pixels limit (max_image_pixels" in err, err


def test_a_misspelt_variable_is_refused_by_the_installed_command(tmp_path):
    """J4 as reported, in a process of its own (the bounds read at its start): one line naming
    the variable, exit 2, before the map or the image is looked at."""
    env = {**os.environ, "PYTHONPATH": str(REPO), "SLAMRELOC_max_image_pixels": "1000"}
    done = subprocess.run([sys.executable, "-m", "slamreloc.cli", "localize",
                           str(tmp_path / "no-map"), str(tmp_path / "no.png")],
                          capture_output=True, text=True, env=env, timeout=300)
    assert done.returncode == 2, done.stderr
    assert done.stderr.strip().splitlines() == [
        f"error: {resembles_bound('SLAMRELOC_max_image_pixels', 'max_image_pixels')}"]


@st.composite
def respelt(draw, exact: str) -> str:
    """`exact` with each letter in either case and any of "", "_", "-", "__" between letters."""
    letters = [c for c in exact if c.isalnum()]
    out = []
    for i, c in enumerate(letters):
        if i:
            out.append(draw(st.sampled_from(["", "_", "-", "__"])))
        out.append(c.lower() if draw(st.booleans()) else c.upper())
    return "".join(out)


@given(st.sampled_from(BOUNDS).flatmap(
    lambda bound: st.tuples(st.just(bound), respelt(f"SLAMRELOC_{bound.upper()}"))))
@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.filter_too_much])
def test_every_other_spelling_of_a_bound_is_refused_naming_it(case):
    """J4's class: a bound's variable spelt but for case and underscores names that bound in
    its refusal; only the exact name is taken."""
    bound, name = case
    exact = f"SLAMRELOC_{bound.upper()}"
    if name == exact:
        assert environment_problem(name) is None
        return
    assert environment_problem(name) == resembles_bound(name, bound)
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv(name, "1000")
        with pytest.raises(InputError) as refused:
            check_environment()
    assert str(refused.value) == resembles_bound(name, bound)


@given(st.sampled_from(sorted(KNOWN_VARIABLES)).flatmap(
    lambda known: st.tuples(st.just(known), respelt(known))))
@settings(max_examples=150, deadline=None)
def test_every_other_spelling_of_a_known_variable_is_refused_naming_it(case):
    """SLAMRELOC_TOKEN and the other known variables: `slamreloc_token` was ignored, the
    service then ran without the token the user meant to set."""
    known, name = case
    if name == known:
        assert environment_problem(name) is None
        return
    assert environment_problem(name) == (f"environment variable {name} names no slamreloc "
                                         f"setting: it resembles {known}, a name read exactly "
                                         "as spelt")


@given(st.lists(st.booleans(), min_size=9, max_size=9),
       st.from_regex(r"[A-Za-z0-9_]{0,30}", fullmatch=True))
@settings(max_examples=300, deadline=None)
def test_any_unknown_slamreloc_name_is_refused(lower, rest):
    """Any name starting SLAMRELOC_ in any case that is no bound's and no known variable is
    refused, naming it (a setting the package does not read is one the user believes holds)."""
    name = "".join(c.lower() if low else c for c, low in zip("SLAMRELOC", lower)) + "_" + rest
    assume(name not in BOUND_VARIABLES and name not in KNOWN_VARIABLES)
    problem = environment_problem(name)
    assert problem is not None and problem.startswith(f"environment variable {name} names no ")


@pytest.mark.parametrize("name", ["SLAMRELCO_MAX_IMAGE_PIXELS", "SLAM_MAX_IMAGE_PIXELS",
                                  "SLAMRELOCMAX_IMAGE_PIXELS", "Slam-Reloc-Max-Image-Pixels",
                                  "SLAMRELOC_MAX_IMAGE_PIXELSS"])
def test_a_bound_with_its_prefix_misspelt_is_refused_naming_it(name):
    assert environment_problem(name) == resembles_bound(name, "max_image_pixels")


@given(st.from_regex(r"[A-Za-z_][A-Za-z0-9_]{0,7}", fullmatch=True))
@settings(max_examples=200, deadline=None)
def test_other_programs_variables_are_left_alone(name):
    """Names that are not slamreloc's are no concern of it (eight characters or fewer cannot
    resemble a SLAMRELOC_ name)."""
    assert environment_problem(name) is None


@pytest.mark.parametrize("name", ["PATH", "HOME", "RAY_ADDRESS", "OMP_NUM_THREADS",
                                  "RAY_SERVE_GRPC_MAX_MESSAGE_SIZE", "MAX_IMAGE_PIXELS",
                                  "RELOC_MAX_IMAGE_PIXELS", "RELOC_TOKEN", "SLAM_HOME",
                                  "PYTEST_CURRENT_TEST", "CUDA_VISIBLE_DEVICES"])
def test_common_variables_are_left_alone(name):
    """Other programs' names, even near ours, are no concern of slamreloc's: only a name that
    starts with SLAM is compared letter by letter."""
    assert environment_problem(name) is None


def test_every_exact_name_is_taken_and_its_value_read(monkeypatch, fresh_limits):
    """The bounds' variables hold as documented (each bound its own value), the known
    variables pass the check."""
    for i, name in enumerate(BOUND_VARIABLES):
        monkeypatch.setenv(name, str(40 + i))
    for name in KNOWN_VARIABLES:
        monkeypatch.setenv(name, "")
    check_environment()
    assert asdict(limits()) == {bound: 40 + i for i, bound in enumerate(BOUND_VARIABLES.values())}


def _source_files(*roots: str):
    skip = {".git", "__pycache__", ".hypothesis", "tests", "node_modules", "build"}
    for root in roots:
        top = REPO / root
        paths = [top] if top.is_file() else top.rglob("*") if top.is_dir() else []
        for path in paths:
            if path.is_file() and not skip & set(path.relative_to(REPO).parts) and \
                    path.suffix in {"", ".py", ".cpp", ".h", ".hpp", ".inc", ".md", ".txt",
                                    ".sh", ".yaml", ".yml", ".toml", ".cfg", ".ini", ".cmake"}:
                yield path


def test_every_slamreloc_variable_the_project_reads_is_known():
    """One list (`KNOWN_VARIABLES`, with the bounds' `BOUND_VARIABLES`): every SLAMRELOC_ name
    in the package, the clients, the docs, the scripts and CI, and every one the tests read
    from the environment, is in it (a new variable cannot be read and then refused), and it
    holds none that nothing reads."""
    name = re.compile(r"\bSLAMRELOC_[A-Z0-9_]*[A-Z0-9]\b")
    found: dict[str, str] = {}
    the_list = REPO / "slamreloc" / "io" / "limits.py"
    for path in _source_files("slamreloc", "clients", "docs", "scripts", ".ci", "deploy",
                              "benchmarks", "plugins", "viewer", "pseudo_label", "README.md",
                              "BENCHMARKS.md", "Makefile", "pyproject.toml"):
        for n in name.findall(path.read_text(errors="replace") if path != the_list else ""):
            found.setdefault(n, str(path.relative_to(REPO)))
    read = re.compile(r"""(?:environ\.get|getenv|environ\[)\(?\s*["'](SLAMRELOC_\w+)""")
    for path in (REPO / "tests").glob("*.py"):
        for n in read.findall(path.read_text()):
            found.setdefault(n, str(path.relative_to(REPO)))
    assert {"SLAMRELOC_TOKEN", "SLAMRELOC_TEST_CRASH_AT", "SLAMRELOC_NO_RENAME_EXCHANGE",
            "SLAMRELOC_DOCS_SLOW", "SLAMRELOC_MAX_IMAGE_PIXELS"} <= set(found)  # the search works
    unknown = {n: where for n, where in found.items()
               if n not in KNOWN_VARIABLES and n not in BOUND_VARIABLES}
    assert not unknown, f"add to slamreloc.io.limits.KNOWN_VARIABLES: {unknown}"
    unused = set(KNOWN_VARIABLES) - set(found)
    assert not unused, f"read nowhere, left in KNOWN_VARIABLES: {unused}"


def test_the_suites_own_environment_holds_no_stray_name():
    """Every command the suite runs checks the environment it inherits: a stray SLAMRELOC_
    name here would fail them all, each for the wrong reason."""
    check_environment()


# ---- J3: a Ray Serve map replica holds its driver's bounds -------------------------------------
def test_a_map_replica_holds_the_bounds_it_is_given_not_its_environment(tiny_map, monkeypatch,
                                                                        fresh_limits):
    """J3: the replica read its own environment (the driver's `--limit` never reached it). It
    now holds the bounds `deploy` hands it, in both directions, before it reads its map, even
    where its environment says otherwise or holds a stray name."""
    pytest.importorskip("ray.serve")
    from slamreloc.proto import relocalizer_pb2 as pb
    from slamreloc.service.ray_app import MapReplica

    monkeypatch.setenv("SLAMRELOC_MAX_IMAGE_PIXELS", str(1 << 24))
    monkeypatch.setenv("SLAMRELOC_MIN_IMAGE_SIDE", "16")
    monkeypatch.setenv("SLAMRELOC_max_json_bytes", "5")  # the driver's concern, not the replica's
    driver = replace(InputLimits(), max_image_pixels=1000, min_image_side=8)
    replica = MapReplica.func_or_class("m", str(tiny_map), 0, asdict(driver))
    assert limits() == driver

    def answer(width, height):
        request = pb.LocalizeRequest(image=pb.Image(encoded=png(width, height)))
        return replica.localize(request.SerializeToString())

    kind, message = answer(64, 48)  # 3072 pixels: over the driver's bound, under the variable's
    assert kind == pb.TOO_LARGE and message.decode().startswith(
        "image: image is 64x48 = 3072 pixels, over the 1000 pixels limit (max_image_pixels"), \
        message
    kind, message = answer(12, 9)  # under the variable's 16 a side, over the driver's 8
    assert not (kind and b"a side" in message), message
    # without bounds (a Serve config file) the replica reads its environment, and says so
    monkeypatch.setattr(limits_module, "_current", None)
    with pytest.raises(InputError, match="^environment variable SLAMRELOC_max_json_bytes names "
                                         "no bound: it resembles the bound max_json_bytes"):
        MapReplica.func_or_class("m", str(tiny_map), 0, None)


def test_serve_engine_ray_hands_the_global_limit_to_the_replicas(tiny_map, tmp_path,
                                                                 monkeypatch):
    """J3 through the CLI: `slamreloc --limit max_image_pixels=1000 serve MAP --engine ray`
    deploys map replicas bound by the driver's bounds (the `--limit` and the rest as in
    force); the application is built and inspected, nothing is started."""
    pytest.importorskip("ray.serve")
    from slamreloc.service import ray_serve

    seen = {}
    real = ray_serve.application

    def application(maps, replicas, **kwargs):
        seen.update(kwargs)
        real(maps, replicas, **kwargs)  # the real one takes them
        raise InputError("built")  # before Ray starts

    monkeypatch.setattr(ray_serve, "application", application)
    token = tmp_path / "token.txt"
    token.write_text("a-token-of-enough-characters\n")
    before = limits()
    code, err = run_cli(["--limit", "max_image_pixels=1000", "--limit", "max_json_depth=32",
                         "serve", str(tiny_map), "--engine", "ray", "--token-file", str(token),
                         "--port", "0"])
    assert code == 2 and err.strip().splitlines()[-1] == "error: built", err
    assert seen["bounds"] == replace(before, max_image_pixels=1000, max_json_depth=32)
