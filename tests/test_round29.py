"""Attack round 29: around round 28's fixes.
K1: the fold check took lenses whose circle pixels undistort onto another branch of the lens
(a strong pincushion: a direction 22 degrees off, with an exact round trip).
K2, K3: plain (ASCII) PNMs were scaled twice, and samples over the maxval clamped, by OpenCV.
K4, K5: BMPs of bit fields were decoded by OpenCV ignoring the masks, or not at all.
K6: a TIFF of signed 16-bit samples was said to hold 32-bit ones.
L2: a bad `extended.dataset_roots` entry was named by a field that does not exist.
L3: the C++ client printed names raw: a file name holding a line break forged an output line.
(L1, a session sharing names across the map's datasets: tests/test_live_map.py.)"""
from __future__ import annotations

import json
import shutil
import struct
import subprocess
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from slamreloc.camera_models import fold_problem, undistort_normalized
from slamreloc.cli.jobs import line_name
from slamreloc.errors import InputError
from slamreloc.io.images import read_depth, read_image
from tests.fuzzing import run_cli
from tests.test_cpp_client import MISSING
from tests.test_round26_cpp import fake_server  # noqa: F401 (a fixture)

needs_cpp = pytest.mark.skipif(bool(MISSING), reason=f"the C++ client needs {', '.join(MISSING)}")


# ---- K1 ------------------------------------------------------------------------------------
def test_a_pincushion_undone_on_another_branch_is_refused():
    assert "folds back inside the image" in fold_problem(
        "OPENCV", (1.0, -0.3, 0.0, 0.0), 640, 480, 150, 150, 320.5, 240.5)


@given(k1=st.floats(-1, 1), k2=st.floats(-1, 1), f=st.floats(100, 600),
       cx=st.sampled_from([159.5, 60.0, -40.0]))
@settings(max_examples=80, deadline=None)
def test_a_radial_lens_taken_undistorts_its_circle_on_the_lens_s_own_branch(k1, k2, f, cx):
    """For a radial lens (r_d = r (1 + k1 r^2 + k2 r^4)) the check takes, each pixel of the
    image's inscribed circle undistorts to an ideal radius below the one where r_d first stops
    growing: the direction the lens gives it, not one beyond its field."""
    if fold_problem("OPENCV", (k1, k2, 0.0, 0.0), 320, 240, f, f, cx, 119.5):
        return
    r = np.linspace(0, 50, 200001)
    grows = np.diff(r * (1 + k1 * r ** 2 + k2 * r ** 4)) > 0
    peak = r[np.argmin(grows)] if not grows.all() else np.inf
    angles = np.linspace(0, 2 * np.pi, 120, endpoint=False)
    radius = np.linspace(0, 119.5, 30)[:, None]
    pixels = np.stack([159.5 + radius * np.cos(angles), 119.5 + radius * np.sin(angles)],
                      -1).reshape(-1, 2) - [cx, 119.5]
    ideal = undistort_normalized("OPENCV", (k1, k2, 0.0, 0.0), pixels / f)
    assert np.hypot(*ideal.T).max() <= peak * 1.001


# ---- K2, K3 --------------------------------------------------------------------------------
def _plain_pnm(path: Path, samples: np.ndarray, maxval: int) -> Path:
    """`samples` (H, W) grey or (H, W, 3) RGB whole numbers as a plain (ASCII) PNM, with a
    comment in the header and short lines, as netpbm writes them."""
    magic = "P3" if samples.ndim == 3 else "P2"
    height, width = samples.shape[:2]
    words = [str(int(v)) for v in samples.reshape(-1)]
    lines = [" ".join(words[i:i + 12]) for i in range(0, len(words), 12)]
    path.write_text(f"{magic}\n# a comment\n{width} {height}\n{maxval}\n" + "\n".join(lines)
                    + "\n")
    return path


@pytest.mark.parametrize("maxval", [1, 15, 100, 255, 1000, 65535])
@pytest.mark.parametrize("colour", [True, False], ids=["P3", "P2"])
def test_plain_pnm_samples_are_scaled_by_their_maxval_once(tmp_path, maxval, colour):
    rng = np.random.default_rng(maxval)
    samples = rng.integers(0, maxval + 1, (24, 32, 3) if colour else (24, 32))
    image = read_image(_plain_pnm(tmp_path / "p.pnm", samples, maxval))
    rgb = samples if colour else np.dstack([samples] * 3)
    assert np.abs(image.astype(float) - rgb / maxval * 255).max() <= 0.5 + 1e-9


def test_a_plain_pnm_sample_over_its_maxval_is_refused(tmp_path):
    samples = np.zeros((24, 32, 3), np.int64)
    samples[3, 4, 0] = 60000
    with pytest.raises(InputError, match=r"p\.ppm: not a readable image \(a PNM sample of "
                                         r"60000 is over the maxval 1000"):
        read_image(_plain_pnm(tmp_path / "p.ppm", samples, 1000))


def test_a_plain_pgm_depth_map_is_raw_and_checked(tmp_path):
    mm = np.full((24, 32), 1500)
    assert read_depth(_plain_pnm(tmp_path / "d.pgm", mm, 5000))[2, 2] == pytest.approx(1.5)
    mm[0, 0] = 9000
    with pytest.raises(InputError, match="a PNM sample of 9000 is over the maxval 5000"):
        read_depth(_plain_pnm(tmp_path / "e.pgm", mm, 5000))


# ---- K4, K5 --------------------------------------------------------------------------------
def _bitfields_bmp(path: Path, rgb: np.ndarray, bits: int, masks: tuple[int, int, int],
                   v5: bool) -> Path:
    """A bottom-up BI_BITFIELDS BMP of `rgb` (H, W, 3 uint8) with the channel masks given,
    the samples cut to each mask's width; a BITMAPV5HEADER (masks inside it) or an
    info header followed by the three masks."""
    height, width = rgb.shape[:2]
    words = np.zeros((height, width), np.uint32)
    for channel, mask in enumerate(masks):
        shift, size = (mask & -mask).bit_length() - 1, bin(mask).count("1")
        words |= (rgb[..., channel].astype(np.uint32) >> (8 - size)) << shift
    row = words[::-1].astype("<u2" if bits == 16 else "<u4")
    stride = (width * bits // 8 + 3) // 4 * 4
    pixels = b"".join(r.tobytes().ljust(stride, b"\0") for r in row)
    if v5:
        info = struct.pack("<IiiHHIIiiII", 124, width, height, 1, bits, 3, len(pixels), 2835,
                           2835, 0, 0) + struct.pack("<IIII", *masks, 0) + b"BGRs" + bytes(48)
        info = info.ljust(124, b"\0")
        extra = b""
    else:
        info = struct.pack("<IiiHHIIiiII", 40, width, height, 1, bits, 3, len(pixels), 2835,
                           2835, 0, 0)
        extra = struct.pack("<III", *masks)
    offset = 14 + len(info) + len(extra)
    path.write_bytes(struct.pack("<2sIHHI", b"BM", offset + len(pixels), 0, 0, offset) + info
                     + extra + pixels)
    return path


@pytest.mark.parametrize("bits, masks, v5, step", [
    (32, (0xFF000000, 0x00FF0000, 0x0000FF00), False, 1),  # K4: XBGR, OpenCV read it as BGRX
    (16, (0xF800, 0x07E0, 0x001F), True, 8),  # K5: GIMP's 5-6-5 with a V5 header
], ids=["32-bit XBGR", "16-bit 565 V5"])
def test_a_bitfields_bmp_gives_its_picture(tmp_path, bits, masks, v5, step):
    """The picture the masks describe, to within the samples' own width (a 5-bit channel
    holds steps of 8)."""
    rng = np.random.default_rng(bits)
    rgb = rng.integers(0, 256, (24, 32, 3), dtype=np.uint8)
    image = read_image(_bitfields_bmp(tmp_path / "b.bmp", rgb, bits, masks, v5))
    assert np.abs(image.astype(int) - rgb).max() < step + 4 * (step > 1)


# ---- K6 ------------------------------------------------------------------------------------
def test_a_signed_tiff_is_refused_saying_so(tmp_path):
    path = tmp_path / "s.tif"
    cv2.imwrite(str(path), (np.arange(48 * 64).reshape(48, 64) % 3000 - 1500).astype(np.int16))
    with pytest.raises(InputError, match=r"s\.tif: not a readable image \(a TIFF of 16-bit "
                                         r"signed samples; save it with unsigned 8 or 16 bits\)"):
        read_image(path)
    cv2.imwrite(str(tmp_path / "u.tif"), np.full((48, 64), 30000, np.uint16))
    assert read_image(tmp_path / "u.tif")[0, 0, 0] == round(30000 / 65535 * 255)


# ---- L2 ------------------------------------------------------------------------------------
def test_an_extended_root_is_named_by_its_own_field(small_map, tmp_path):
    bad = tmp_path / "m"
    shutil.copytree(small_map.root, bad)
    meta = json.loads((bad / "slamreloc_map.json").read_text())
    meta["extended"] = {"source_map": "/m", "dataset_roots": ["/a", "rel/b"],
                        "n_prior_frames": 1}
    (bad / "slamreloc_map.json").write_text(json.dumps(meta))
    code, err = run_cli(["export", str(bad), "--tum", str(tmp_path / "t.txt")])
    assert code == 2
    assert err.strip().splitlines()[-1].startswith(
        f"error: {bad / 'slamreloc_map.json'}: 'extended.dataset_roots[1]' must be an absolute "
        "path"), err


# ---- L3 ------------------------------------------------------------------------------------
@needs_cpp
def test_the_cpp_client_prints_names_by_the_cli_s_rule(client_binary, fake_server,  # noqa: F811
                                                       tmp_path):
    """A 7-Scenes folder's file names go out as `slamreloc localize` writes them
    (`line_name`): percent-encoded where they hold a space, a '%', a line break, a character
    Python does not print, or start with '#' - never a line of their own."""
    names = ["frame-0\nfake.png 9 9 9 0 0 0 1 999\nframe-.color.png",
             "frame-1 a%b.color.png", "frame-2\u200b.color.png", "frame-3\u00e9.color.png",
             "frame-4.color.png"]
    png = cv2.imencode(".png", np.zeros((240, 320, 3), np.uint8))[1].tobytes()
    for name in names:
        (tmp_path / name).write_bytes(png)
    done = subprocess.run([str(client_binary), "--server", fake_server, "--timeout", "20",
                           str(tmp_path)], capture_output=True, text=True, timeout=60,
                          check=False)
    assert done.returncode == 0, done.stderr
    assert done.stdout.splitlines() == [f"# {line_name(n)}: not localized (0 inliers)"
                                        for n in sorted(names)]
