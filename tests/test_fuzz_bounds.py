"""Bounds on untrusted input, fuzzed (hypothesis, derandomized): images whose headers claim
more pixels than the bounds allow (decompression bombs) under a memory cap, images too small to
hold a feature, JSON reports of the wrong shape or nested too deep, map metadata with values of
the wrong type or range, cameras with NaN or absurd values, COLMAP poses that are not rotations,
outputs aimed inside inputs; and the property that a command which only reads its inputs leaves
them byte-identical, whatever it is given.

A case passes when the code either works or raises InputError (the CLI: exit 2 and one line
`error: <file>: <problem>` naming the bad file); anything else fails the test.
"""

from __future__ import annotations

import hashlib
import json
import os
import resource
import shutil
import struct
import subprocess
import sys
import tempfile
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from slamreloc.errors import InputError
from slamreloc.io.images import read_image
from slamreloc.io.limits import InputLimits, limits, parse_limits, set_limits
from slamreloc.map.format import META
from slamreloc.map.scene_map import SceneMap
from slamreloc.types import Camera
from tests.fuzzing import COUNTS, fuzz_settings, no_hang, run_cli

MEMORY_TARGET = 2 << 30  # no bad input may take a command past 2 GB (peak RSS)
ADDRESS_CAP = 3 << 30  # the hard cap the bomb runs under: a miss fails the run, not the machine


def _record(fmt: str, outcome: str) -> None:
    COUNTS[(fmt, outcome)] += 1


@pytest.fixture(autouse=True)
def _default_limits():
    """Every test starts from the default bounds (the CLI's --limit sets them per process)."""
    set_limits(**vars(InputLimits()))
    yield
    set_limits(**vars(InputLimits()))


# --- decompression bombs ---------------------------------------------------------------------

def _png_chunk(kind: bytes, payload: bytes) -> bytes:
    return (struct.pack(">I", len(payload)) + kind + payload
            + struct.pack(">I", zlib.crc32(kind + payload)))


def bomb_png(width: int, height: int, bits: int, colour: int) -> bytes:
    """A complete, CRC-valid PNG that claims width x height; its pixel data is a few rows (the
    decoder allocates the whole image before it finds out)."""
    row = b"\x00" * (1 + width * {0: 1, 2: 3, 4: 2, 6: 4}[colour] * bits // 8)
    data = zlib.compress(row * 4, 9)
    return (b"\x89PNG\r\n\x1a\n"
            + _png_chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, bits, colour, 0, 0, 0))
            + _png_chunk(b"IDAT", data) + _png_chunk(b"IEND", b""))


def bomb_jpeg(width: int, height: int, grey: bool) -> bytes:
    """A real 16x16 JPEG whose frame header is rewritten to claim width x height."""
    img = np.full((16, 16) if grey else (16, 16, 3), 128, np.uint8)
    data = bytearray(cv2.imencode(".jpg", img)[1].tobytes())
    sof = data.index(b"\xff\xc0")
    data[sof + 5:sof + 9] = struct.pack(">HH", height, width)
    return bytes(data)


def bomb_bmp(width: int, height: int) -> bytes:
    pixels = b"\x00" * 64
    header = struct.pack("<2sIHHI", b"BM", 54 + len(pixels), 0, 0, 54)
    info = struct.pack("<IiiHHIIiiII", 40, width, height, 1, 24, 0, len(pixels), 2835, 2835, 0, 0)
    return header + info + pixels


def bomb_tiff(width: int, height: int) -> bytes:
    """A little-endian baseline TIFF (one strip, 8-bit grey) with a few bytes of pixels."""
    entries = [(256, 4, 1, width), (257, 4, 1, height), (258, 3, 1, 8), (259, 3, 1, 1),
               (262, 3, 1, 1), (273, 4, 1, 8 + 2 + 12 * 9 + 4), (277, 3, 1, 1),
               (278, 4, 1, height), (279, 4, 1, 64)]
    ifd = struct.pack("<H", len(entries)) + b"".join(
        struct.pack("<HHII", tag, kind, count, value) for tag, kind, count, value in entries)
    return b"II*\x00" + struct.pack("<I", 8) + ifd + struct.pack("<I", 0) + b"\x00" * 64


def bomb_pnm(width: int, height: int) -> bytes:
    return f"P6\n{width} {height}\n255\n".encode() + b"\x00" * 64


def bomb_webp(width: int, height: int) -> bytes:
    """A lossless WebP (VP8L) header claiming width x height (each at most 16384)."""
    bits = (width - 1) | ((height - 1) << 14)
    payload = b"\x2f" + struct.pack("<I", bits) + b"\x00" * 32
    chunk = b"VP8L" + struct.pack("<I", len(payload)) + payload
    return b"RIFF" + struct.pack("<I", 4 + len(chunk)) + b"WEBP" + chunk


@st.composite
def bomb(draw) -> tuple[str, bytes]:
    """(file suffix, bytes) of an image whose header asks for more pixels than the default
    bound, or has a side under the minimum."""
    fmt = draw(st.sampled_from(["png", "png", "jpg", "jpg", "bmp", "tif", "ppm", "webp"]))
    top = 16384 if fmt == "webp" else 65500
    pixels = limits().max_image_pixels
    if draw(st.integers(0, 3)) == 0:  # a side too small
        width, height = draw(st.integers(1, 15)), draw(st.integers(1, top))
    else:  # too many pixels
        width = draw(st.integers(pixels // top + 1, top))
        height = draw(st.integers(pixels // width + 1, top))
    if draw(st.booleans()):
        width, height = height, width
    if fmt == "png":
        bits, colour = draw(st.sampled_from([(8, 0), (8, 2), (16, 2), (8, 6), (16, 6), (16, 0)]))
        return fmt, bomb_png(width, height, bits, colour)
    if fmt == "jpg":
        return fmt, bomb_jpeg(width, height, draw(st.booleans()))
    return fmt, {"bmp": bomb_bmp, "tif": bomb_tiff, "ppm": bomb_pnm,
                 "webp": bomb_webp}[fmt](width, height)


def _run_capped(argv: list[str], env: dict | None = None) -> tuple[int, str, str, int]:
    """Run a command under the address-space cap: (exit status, stdout, stderr, peak RSS
    bytes)."""
    def cap():
        resource.setrlimit(resource.RLIMIT_AS, (ADDRESS_CAP, ADDRESS_CAP))

    with tempfile.TemporaryFile() as out, tempfile.TemporaryFile() as err:
        proc = subprocess.Popen(argv, stdout=out, stderr=err, preexec_fn=cap,
                                env={**os.environ, **(env or {})})
        try:
            _, status, usage = os.wait4(proc.pid, 0)
        finally:
            proc.returncode = 0  # reaped by wait4
        out.seek(0)
        err.seek(0)
        return (os.waitstatus_to_exitcode(status), out.read().decode(), err.read().decode(),
                usage.ru_maxrss * 1024)


@pytest.fixture(scope="module")
def bombs(tmp_path_factory) -> list[Path]:
    folder = tmp_path_factory.mktemp("bombs")
    made: list[Path] = []

    @fuzz_settings(60)
    @given(case=bomb())
    def write(case):
        suffix, data = case
        path = folder / f"bomb-{len(made):03d}.{suffix}"
        path.write_bytes(data)
        made.append(path)

    write()
    return made


def test_decompression_bombs_are_refused_before_decoding(small_map, bombs):
    """`slamreloc localize` on every generated bomb, in one process under a 3 GB address-space
    cap: each is refused with one error line naming it, and the process stays under 2 GB."""
    code, out, err, peak = _run_capped(
        [sys.executable, "-m", "slamreloc.cli", "localize", str(small_map.root),
         *map(str, bombs)])
    assert "Traceback" not in err, err[-2000:]
    assert code == 2, err[-2000:]
    errors = [ln for ln in err.splitlines() if ln.startswith("error: ")]
    for path in bombs:
        named = [ln for ln in errors if f"{path}:" in ln]
        assert len(named) == 1, (path, err[-2000:])
        _record("image_bomb", "refused")
    assert len(errors) == len(bombs)
    assert peak < MEMORY_TARGET, f"peak RSS {peak / 1e9:.2f} GB"


def test_bombs_are_refused_in_process_by_every_image_reader(bombs, tmp_path):
    """The readers behind every command (colour, depth, header) refuse each bomb from its
    header: refusing reads no pixels, so this runs in the test process itself."""
    from slamreloc.io.images import image_header, read_depth

    for path in bombs:
        for read in (read_image, read_depth, image_header):
            with no_hang(10), pytest.raises(InputError, match=str(path)):
                read(path)


def test_images_at_the_bounds_fit_in_memory(small_map, tmp_path):
    """The largest image each bound lets through keeps `localize` under 2 GB: the small map
    (SIFT with upsampling, 240 B a pixel) takes images up to max_feature_bytes / 240 pixels;
    one pixel side more is refused by the feature bound, not by running out of memory."""
    per_px = small_map_working_bytes(small_map)
    aspect = small_map.camera.width / small_map.camera.height  # the map's camera fits both
    h = int((limits().max_feature_bytes / per_px / aspect) ** 0.5)
    w = int(h * aspect)
    rng = np.random.default_rng(0)
    texture = (rng.random((h // 8, w // 8)) * 255).astype(np.uint8)
    ok = cv2.resize(texture, (w, h), interpolation=cv2.INTER_LINEAR)
    cv2.imwrite(str(tmp_path / "ok.png"), ok)
    cv2.imwrite(str(tmp_path / "over.png"), cv2.resize(ok, (round((h + 8) * aspect), h + 8)))
    code, out, err, peak = _run_capped(
        [sys.executable, "-m", "slamreloc.cli", "localize", str(small_map.root),
         str(tmp_path / "ok.png"), str(tmp_path / "over.png")])
    assert "Traceback" not in err, err[-2000:]
    assert "ok.png" in out and "over.png" not in out  # a pose or "not localized"
    assert [ln for ln in err.splitlines() if ln.startswith("error: ")] == [
        ln for ln in err.splitlines() if "over.png" in ln and "max_feature_bytes" in ln]
    assert peak < MEMORY_TARGET, f"peak RSS {peak / 1e9:.2f} GB"


def small_map_working_bytes(scene_map: SceneMap) -> int:
    from slamreloc.features import make_extractor

    ex = make_extractor(scene_map.info.feature_name, **scene_map.info.feature_options)
    return ex.working_pixels(1, 1) * ex.bytes_per_pixel


def test_limit_flag_raises_a_bound(small_map, tmp_path):
    """`--limit max_image_pixels=N` lets a larger image through; a bad --limit is one line."""
    big = tmp_path / "big.png"  # the map camera's aspect ratio: 0.31 MP, over a 0.2 MP bound
    cv2.imwrite(str(big), np.zeros((480, 640), np.uint8))
    code, err = cli(["--limit", "max_image_pixels=200000", "localize", str(small_map.root),
                     str(big)])
    assert code == 2 and "--limit max_image_pixels=N" in err and str(big) in err
    code, err = cli(["--limit", "max_image_pixels=400000", "localize", str(small_map.root),
                     str(big)])
    assert code == 0, err
    for bad in ("max_image_pixels", "nope=3", "max_image_pixels=-1", "max_image_pixels=abc"):
        code, err = cli(["--limit", bad, "localize", str(small_map.root), str(big)])
        assert code == 2 and err.count("\n") == 1 and "--limit" in err


def test_limits_from_the_environment():
    assert parse_limits(["max_json_depth=12"]) == {"max_json_depth": 12}
    code = ("import os; os.environ['SLAMRELOC_MAX_IMAGE_PIXELS'] = '1000000';"
            "from slamreloc.io.limits import limits; print(limits().max_image_pixels)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "1000000"


# --- the CLI in process -----------------------------------------------------------------------

def cli(argv: list[str]) -> tuple[int, str]:
    code, err = run_cli(argv, 120)
    assert "Traceback" not in err, err
    return code, err


def one_error_naming(code: int, err: str, *names) -> None:
    lines = [ln for ln in err.splitlines() if ln.strip()]
    errors = [ln for ln in lines if ln.startswith("error: ")]
    assert code == 2 and len(errors) == 1, err
    assert any(str(n) in errors[0] for n in names), (names, errors[0])


# --- cameras ----------------------------------------------------------------------------------

finite_or_not = st.one_of(st.floats(allow_nan=True, allow_infinity=True),
                          st.integers(-(1 << 80), 1 << 80), st.sampled_from([0, -1, 1e308]))


@fuzz_settings(300)
@given(values=st.tuples(finite_or_not, finite_or_not, finite_or_not, finite_or_not))
def test_fuzz_camera_values(values):
    """A camera is made only from finite, in-range values; anything else is an InputError."""
    try:
        cam = Camera(640, 480, *values)
        outcome = "loaded"
    except InputError:
        outcome = "refused"
    if outcome == "loaded":
        assert all(np.isfinite(cam.params())) and cam.fx > 0 and cam.fy > 0
    _record("camera", outcome)


@pytest.mark.parametrize("values", [["nan", "nan", "320", "240"], ["inf", "500", "1", "1"],
                                    ["500", "-1", "320", "240"], ["500", "500", "1e300", "2"]])
def test_cli_intrinsics_must_be_finite_and_positive(small_map, scene_dir, values):
    image = next((scene_dir / "seq-02").glob("*.color.png"))
    code, err = cli(["localize", str(small_map.root), str(image), "--intrinsics", *values])
    one_error_naming(code, err, "--intrinsics")


# --- COLMAP poses -----------------------------------------------------------------------------

@fuzz_settings(60)
@given(q=st.one_of(st.just((0.0, 0.0, 0.0, 0.0)),
                   st.tuples(*[st.floats(-3, 3, allow_nan=False)] * 4).filter(
                       lambda q: abs(sum(v * v for v in q) ** 0.5 - 1) > 2e-3),
                   st.tuples(st.just(float("nan")), st.floats(-1, 1), st.floats(-1, 1),
                             st.floats(-1, 1))),
       binary=st.booleans())
def test_fuzz_colmap_quaternion_must_be_unit(tmp_path_factory, q, binary):
    """An image whose quaternion is zero, NaN or far from unit norm is refused, naming the file
    (and, in text models, the line): normalising it would make up a pose."""
    from slamreloc.datasets.colmap_check import check_model

    folder = tmp_path_factory.mktemp("colmapq")
    qtext = " ".join(repr(float(v)) for v in q)
    if binary:
        (folder / "cameras.bin").write_bytes(
            struct.pack("<QIiQQ4d", 1, 1, 1, 64, 48, 60.0, 60.0, 32.0, 24.0))
        (folder / "images.bin").write_bytes(
            struct.pack("<QI7dI", 1, 1, *q, 0.0, 0.0, 0.0, 1) + b"a.png\x00"
            + struct.pack("<Q", 0))
    else:
        (folder / "cameras.txt").write_text("1 PINHOLE 64 48 60 60 32 24\n")
        (folder / "images.txt").write_text(f"1 {qtext} 0 0 0 1 a.png\n\n")
    ext = "bin" if binary else "txt"
    with pytest.raises(InputError, match=f"images.{ext}"):
        check_model(folder, ext)
    _record("colmap_pose", "refused")


# --- outputs aimed at inputs ------------------------------------------------------------------

def _snapshot(*roots: Path) -> dict[str, str]:
    """Every file under `roots` (and every folder), with its SHA-256: equal means untouched."""
    snap = {}
    for root in roots:
        for path in sorted(Path(root).rglob("*")):
            snap[str(path)] = ("dir" if path.is_dir() else
                               hashlib.sha256(path.read_bytes()).hexdigest())
    return snap


@pytest.mark.parametrize("where", ["map/new", "map", "dataset/out", "dataset/seq-02"])
def test_pseudo_label_never_writes_into_its_inputs(small_map, scene_dir, tmp_path, where):
    """The map it updates and the dataset it reads stay untouched, whatever --out says."""
    out = {"map": small_map.root, "dataset": scene_dir}[where.split("/")[0]]
    out = out / where.split("/")[1] if "/" in where else out
    before = _snapshot(small_map.root, scene_dir)
    code, err = cli(["pseudo-label", str(small_map.root), str(scene_dir), "--out", str(out),
                     "--report", str(tmp_path / "r.json")])
    one_error_naming(code, err, out)
    assert _snapshot(small_map.root, scene_dir) == before


# --- the read-only property ------------------------------------------------------------------

@st.composite
def read_only_command(draw, map_dir: Path, scene: Path, case: Path) -> list[str]:
    """A read-only command over the map and the scene (evaluate, localize, slam, export, the
    viewer's loader), with outputs anywhere, inputs included (where they must be refused)."""
    out_dir = draw(st.sampled_from([case, map_dir, scene, scene / "seq-02"]))
    name = draw(st.sampled_from(["r.json", META, "frame-000000.pose.txt", "new"]))
    out = out_dir / name
    images = sorted((scene / "seq-02").glob("*.color.png"))[:2]
    kind = draw(st.sampled_from(["evaluate", "evaluate", "localize", "slam", "view-load",
                                 "export"]))
    if kind == "export":
        return ["export", str(map_dir), "--dataset", str(scene), "--ply", str(out)]
    if kind == "evaluate":
        return ["evaluate", str(map_dir), str(scene), "--split", "seq-02", "--report", str(out),
                "--method", draw(st.sampled_from(["regressor", "matching"]))]
    if kind == "localize":
        return ["localize", str(map_dir), *map(str, images)]
    if kind == "slam":
        return ["slam", str(scene), "--map", str(map_dir), "--split", "seq-02", "--report",
                str(out), "--odometry", "open3d"]
    return ["view-load", str(map_dir), str(scene)]


def _damage(draw, root: Path) -> None:
    """Leave the inputs valid, or damage one file (truncate it or flip a byte)."""
    files = sorted(p for p in root.rglob("*") if p.is_file())
    how = draw(st.sampled_from(["none", "none", "truncate", "flip"]))
    if how == "none":
        return
    path = draw(st.sampled_from(files))
    data = path.read_bytes()
    path.unlink()  # a hard-linked copy: replace, never edit in place
    if how == "truncate":
        path.write_bytes(data[:draw(st.integers(0, max(0, len(data) - 1)))])
    else:
        pos = draw(st.integers(0, max(0, len(data) - 1)))
        path.write_bytes(data[:pos] + bytes([(data[pos:pos + 1] or b"\0")[0] ^ 0x40])
                         + data[pos + 1:])


@fuzz_settings(30)
@given(data=st.data())
def test_fuzz_read_only_commands_leave_inputs_byte_identical(small_map, scene_dir, tmp_path_factory,
                                                             data):
    """Whatever a read-only command is given (valid or damaged inputs, outputs aimed anywhere),
    it never changes, adds or removes a file in the map or the dataset it reads."""
    case = tmp_path_factory.mktemp("readonly")
    map_dir, scene = case / "map", case / "scene"
    shutil.copytree(small_map.root, map_dir, copy_function=os.link)
    shutil.copytree(scene_dir, scene, copy_function=os.link,
                    ignore=shutil.ignore_patterns("seq-03", "seq-04"))
    _damage(data.draw, data.draw(st.sampled_from([map_dir, scene])))
    argv = data.draw(read_only_command(map_dir, scene, case))
    before = _snapshot(map_dir, scene)
    if argv[0] == "view-load":
        from slamreloc.viewer.data import ViewerInputs
        from slamreloc.viewer.loaders import load_scene_data

        try:
            load_scene_data(ViewerInputs(map_dir, [], [], scene))
            outcome = "ok"
        except InputError:
            outcome = "refused"
    else:
        code, err = cli(argv)
        assert code in (0, 2), err
        outcome = "ok" if code == 0 else "refused"
    assert _snapshot(map_dir, scene) == before, argv
    _record("read_only", outcome)
    shutil.rmtree(case)


# --- map metadata -----------------------------------------------------------------------------

def _leaf_paths(value, prefix=()):
    if isinstance(value, dict):
        for k, v in value.items():
            yield prefix + (k,)
            yield from _leaf_paths(v, prefix + (k,))


@fuzz_settings(150)
@given(data=st.data())
def test_fuzz_map_metadata_values(small_map, tmp_path_factory, data):
    """Any field of the map's metadata replaced by a value of another type or range: the map
    loads and localizes, or is refused naming its metadata file."""
    meta = json.loads((small_map.root / META).read_text())
    paths = [p for p in _leaf_paths(meta) if p[0] != "files"]
    path = data.draw(st.sampled_from(paths))
    value = data.draw(st.sampled_from(["x", [], {}, None, -1, 0, 1e308, True, 1 << 70,
                                       [1, "a"], 0.5, 1e-9]))
    target = meta
    for key in path[:-1]:
        target = target[key]
    target[path[-1]] = value
    case = tmp_path_factory.mktemp("meta") / "map"
    shutil.copytree(small_map.root, case, copy_function=os.link)
    (case / META).unlink()
    (case / META).write_text(json.dumps(meta))
    image = np.zeros((240, 320, 3), np.uint8)
    cv2.randn(image, 128, 60)
    try:
        with no_hang(60):
            loaded = SceneMap.load(case)
            from slamreloc.localize.localizer import make_localizer

            for method in ("regressor", "matching"):
                make_localizer(loaded, method).localize(image, loaded.camera.scaled_to(320, 240))
        outcome = "loaded"
    except InputError as err:
        assert str(case / META) in str(err) or str(case) in str(err), err
        outcome = "refused"
    _record("map_meta_values", outcome)


# --- report JSON ------------------------------------------------------------------------------

REPORT_FIELDS = {
    "evaluate": {"n_queries": 1, "per_query": [{"name": "seq-02/frame-000000",
                                                "translation_error_m": 0.01,
                                                "rotation_error_deg": 0.5, "num_inliers": 40}]},
    "slam": {"ate_rmse_m": 0.02, "events": [{"frame": 1, "type": "relocalization",
                                              "accepted": True, "position": [0, 0, 1]}],
             "graph_edges": [{"type": "odometry", "a": [0, 0, 0], "b": [0, 0, 1]}],
             "kidnap_frames": [3], "trajectory": "t.txt"},
    "pseudo-label": {"n_pseudo_labels": 3, "poses": {"seq-04/frame-000000": np.eye(4).tolist()}},
}
ODD = st.one_of(st.sampled_from(["x", [], {}, None, -1, 1e308, True, 1 << 70, [[["deep"]]],
                                 {"a": {"b": []}}, [1, "a"], [float("inf")] * 3]),
                st.recursive(st.integers(), lambda c: st.lists(c, max_size=3), max_leaves=5))


def _replace_somewhere(draw, value):
    """`value` with one node (the root's children and below) replaced by an odd value."""
    if isinstance(value, dict) and value:
        key = draw(st.sampled_from(sorted(value)))
        out = dict(value)
        out[key] = _replace_somewhere(draw, value[key]) if draw(st.booleans()) else draw(ODD)
        return out
    if isinstance(value, list) and value:
        i = draw(st.integers(0, len(value) - 1))
        out = list(value)
        out[i] = _replace_somewhere(draw, value[i]) if draw(st.booleans()) else draw(ODD)
        return out
    return draw(ODD)


@fuzz_settings(200)
@given(data=st.data(), kind=st.sampled_from(sorted(REPORT_FIELDS)))
def test_fuzz_viewer_reports(small_map, scene_dir, tmp_path_factory, data, kind):
    """A report of each kind with one field of the wrong type, range or nesting (or nested
    100 000 deep): the viewer's loader reads it or refuses it naming the report."""
    from slamreloc.viewer.data import ViewerInputs
    from slamreloc.viewer.loaders import load_scene_data

    folder = tmp_path_factory.mktemp("report")
    report = folder / "report.json"
    if data.draw(st.integers(0, 9)) == 0:
        depth = data.draw(st.sampled_from([65, 1000, 100_000]))
        text = '{"events": ' + "[" * depth + "]" * depth + "}"
    else:
        content = _replace_somewhere(data.draw, REPORT_FIELDS[kind])
        text = json.dumps(content, allow_nan=True)
    report.write_text(text)
    (folder / "t.txt").write_text("0 0 0 1 0 0 0 1\n1 0 0 1.1 0 0 0 1\n")
    try:
        with no_hang(60):
            load_scene_data(ViewerInputs(small_map.root, [], [report], scene_dir))
        outcome = "loaded"
    except InputError as err:
        assert str(report) in str(err), err
        outcome = "refused"
    _record("report_json", outcome)


# --- the attack classes found by hand, kept as tests --------------------------------------------

@pytest.mark.parametrize("outputs", [["--report", "/dev/null"], ["--trajectory", "/dev/full"],
                                     ["--report", "SAME", "--trajectory", "SAME"],
                                     ["--report", "DIR"]])
def test_outputs_never_replace_devices_folders_or_each_other(small_map, scene_dir, tmp_path,
                                                             outputs):
    """An atomic rename would replace a device with a file, and two outputs of the same path
    would overwrite each other: both are refused before any work."""
    (tmp_path / "DIR").mkdir()
    argv = [{"SAME": str(tmp_path / "same.json"), "DIR": str(tmp_path / "DIR")}.get(a, a)
            for a in outputs]
    if "--report" not in argv:
        argv += ["--report", str(tmp_path / "r.json")]
    before = {p: os.stat(p).st_rdev for p in ("/dev/null", "/dev/full")}
    code, err = cli(["evaluate", str(small_map.root), str(scene_dir), "--split", "seq-02",
                     *argv])
    one_error_naming(code, err, *argv[1::2])
    assert {p: os.stat(p).st_rdev for p in before} == before
    assert not (tmp_path / "same.json").exists()


@pytest.mark.parametrize("name", ["database.npz", "regressor.npz", "surface.npz"])
def test_npz_member_that_is_not_an_array_is_refused(small_map, tmp_path, name):
    """An .npz holding a member that is not .npy data (numpy hands such members back as raw
    bytes), with its checksum rewritten to match: refused naming the file, not a traceback."""
    import zipfile

    case = tmp_path / "map"
    shutil.copytree(small_map.root, case)
    with zipfile.ZipFile(case / name, "a") as zf:
        zf.writestr("extra.bin", b"\x00" * 1000)
    meta = json.loads((case / META).read_text())
    meta["files"][name] = hashlib.sha256((case / name).read_bytes()).hexdigest()
    (case / META).write_text(json.dumps(meta))
    with pytest.raises(InputError, match=f"{case / name}.*not a numpy array"):
        loaded = SceneMap.load(case)  # reads the weights
        _ = loaded.database if name == "database.npz" else loaded.surface


def test_view_refuses_an_unresolvable_host_before_reading(small_map):
    from slamreloc.viewer.data import ViewerInputs
    from slamreloc.viewer.server import start

    with no_hang(30), pytest.raises(InputError, match="`host`"):
        start(ViewerInputs(small_map.root, host="no.such.host.invalid"))


@pytest.mark.parametrize("line", ["0.0 /etc/hostname", "0.0 ../outside.png",
                                  "0.0 rgb/a.png\n0.1 rgb/a.png"])
def test_tum_lists_stay_inside_the_dataset(tmp_path, line):
    from slamreloc.datasets import load_dataset

    (tmp_path / "rgb").mkdir()
    cv2.imwrite(str(tmp_path / "rgb" / "a.png"), np.zeros((48, 64, 3), np.uint8))
    (tmp_path / "rgb.txt").write_text(line + "\n")
    with pytest.raises(InputError, match="rgb.txt"):
        load_dataset(tmp_path)


@pytest.mark.parametrize("k", ["262 5 160\n0 262 120\n0 0 1", "262 0 160\n0 262 120\n5 5 5",
                               "1e-300 0 160\n0 262 120\n0 0 1", "262 0 1e12\n0 262 120\n0 0 1"])
def test_intrinsics_files_are_pinhole_and_in_range(tmp_path, k):
    from slamreloc.datasets import read_intrinsics

    (tmp_path / "intrinsics.txt").write_text(k + "\n")
    with pytest.raises(InputError, match="intrinsics.txt"):
        read_intrinsics(tmp_path / "intrinsics.txt")


@pytest.mark.parametrize("t", ["1e200", "-1e308"])
def test_huge_translations_are_refused(tmp_path, t):
    from slamreloc.geometry import read_tum_trajectory

    (tmp_path / "t.txt").write_text(f"0 {t} 0 0 0 0 0 1\n")
    with pytest.raises(InputError, match="t.txt:1"):
        read_tum_trajectory(tmp_path / "t.txt")


@pytest.mark.parametrize("kind", ["folder", "broken link"])
def test_a_colour_image_that_is_not_a_file_is_named(scene_dir, tmp_path, kind):
    """A frame is never dropped unsaid: a colour image name that is a folder or a link to
    nothing is an error naming it."""
    from slamreloc.datasets import load_dataset

    root = tmp_path / "scene"
    shutil.copytree(scene_dir, root, copy_function=os.link)
    victim = sorted((root / "seq-02").glob("*.color.png"))[3]
    victim.unlink()
    if kind == "folder":
        victim.mkdir()
    else:
        victim.symlink_to(tmp_path / "nothing.png")
    with pytest.raises(InputError, match=victim.name):
        load_dataset(root)
