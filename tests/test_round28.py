"""Attack round 28 (B): the readers of the user's own data.
J1: a fisheye camera whose image reaches past 90 degrees off its axis (the principal point far
off centre) was refused as a lens that "folds back", with a distortion of zeros.
J2: a PNM whose maxval is not 255 or 65535 was decoded as raw samples: a black picture taken.
J7: a BMP Pillow cannot parse (10-bit bitfields) was "not a readable image (OSError)"."""
from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from slamreloc.camera_models import fold_problem
from slamreloc.errors import InputError
from slamreloc.io.images import read_depth, read_image
from tests.fuzzing import run_cli

BEYOND = "the image reaches beyond what the fisheye lens sees"


# ---- J1 ------------------------------------------------------------------------------------
def test_an_off_centre_fisheye_past_90_degrees_is_said_so():
    """The attack's camera: a fisheye of zero distortion cannot fold; its image's circle
    reaches past 90 degrees from a principal point off the image."""
    code, err = run_cli(["localize", "no-map", "x.png", "--camera",
                         "OPENCV_FISHEYE 320 240 433 433 -319.5 -239.5 0 0 0 0"])
    assert code == 2
    line = err.strip().splitlines()[-1]
    assert line.startswith("error: --camera: towards pixel (") and BEYOND in line, err
    assert "fx=433, fy=433); check the focal lengths" in line


@given(f=st.floats(60, 1500), cx=st.floats(-320, 640), cy=st.floats(-240, 480))
@settings(max_examples=150, deadline=None)
def test_a_fisheye_of_zero_distortion_is_never_a_fold(f, cx, cy):
    """An equidistant lens without distortion maps each direction to one radius (theta * f):
    it is taken, or refused because the image reaches past 90 degrees (pi / 2 * f pixels from
    the principal point), never as a fold; and where the image's inscribed circle reaches
    clearly past that, it is refused."""
    problem = fold_problem("OPENCV_FISHEYE", (0.0,) * 4, 320, 240, f, f, cx, cy)
    assert problem is None or BEYOND in problem, problem
    farthest = np.hypot(159.5 - cx, 119.5 - cy) + 120  # of the circle, from (cx, cy)
    if farthest / f > np.pi / 2 * 1.01:
        assert problem is not None


# ---- J2 ------------------------------------------------------------------------------------
def _pnm(path: Path, picture: np.ndarray, maxval: int) -> Path:
    """`picture` (0..1 floats, (H, W) grey or (H, W, 3) RGB) as a binary PNM of `maxval`."""
    samples = np.rint(picture * maxval).astype(">u2" if maxval > 255 else np.uint8)
    magic = b"P6" if picture.ndim == 3 else b"P5"
    height, width = picture.shape[:2]
    path.write_bytes(magic + f"\n# made by a test\n{width} {height}\n{maxval}\n".encode()
                     + samples.tobytes())
    return path


@pytest.mark.parametrize("maxval", [1, 15, 100, 255, 1000, 1023, 4095, 65535])
@pytest.mark.parametrize("colour", [True, False], ids=["P6", "P5"])
def test_pnm_samples_are_scaled_by_their_maxval(tmp_path, maxval, colour):
    """A PNM's sample / maxval is its intensity (the format's definition): every maxval gives
    the same picture, to within its own quantisation."""
    rng = np.random.default_rng(maxval)
    picture = rng.random((48, 64, 3) if colour else (48, 64))
    image = read_image(_pnm(tmp_path / "p.pnm", picture, maxval))
    rgb = picture if colour else np.dstack([picture] * 3)
    expected = np.rint(np.rint(rgb * maxval) / maxval * 255)
    assert image.dtype == np.uint8 and image.shape == (48, 64, 3)
    assert np.abs(image.astype(float) - expected).max() <= 1


def test_a_pnm_sample_over_its_maxval_is_refused(tmp_path):
    path = _pnm(tmp_path / "p.ppm", np.zeros((48, 64, 3)), 15)
    data = bytearray(path.read_bytes())
    data[-1] = 16
    path.write_bytes(bytes(data))
    with pytest.raises(InputError, match=r"p\.ppm: not a readable image \(a PNM sample of 16 "
                                         r"is over the maxval 15 its header declares\)$"):
        read_image(path)


def test_a_pgm_depth_map_keeps_its_raw_units(tmp_path):
    """A depth map's samples are units (millimetres), not intensities: its maxval bounds them
    and scales nothing."""
    mm = np.full((48, 64), 1500, np.uint16)
    mm[0, 0] = 4095
    path = tmp_path / "d.pgm"
    path.write_bytes(b"P5\n64 48\n4095\n" + mm.astype(">u2").tobytes())
    depth = read_depth(path)
    assert depth[1, 1] == pytest.approx(1.5) and depth[0, 0] == pytest.approx(4.095)


# ---- J7 ------------------------------------------------------------------------------------
def test_a_bmp_pillow_cannot_parse_is_named(tmp_path):
    """A 32-bit BI_BITFIELDS BMP of 10-bit samples: Pillow's reason, under the format's name."""
    width, height = 64, 48
    pixels = np.zeros((height, width), "<u4").tobytes()
    info = struct.pack("<IiiHHIIiiII", 40, width, height, 1, 32, 3, len(pixels), 2835, 2835,
                       0, 0)
    masks = struct.pack("<III", 0x3FF00000, 0x000FFC00, 0x000003FF)
    offset = 14 + len(info) + len(masks)
    path = tmp_path / "b.bmp"
    path.write_bytes(struct.pack("<2sIHHI", b"BM", offset + len(pixels), 0, 0, offset)
                     + info + masks + pixels)
    with pytest.raises(InputError, match=r"b\.bmp: not a readable image \(a BMP whose layout "
                                         r"or samples are not read, OSError: Unsupported BMP "
                                         r"bitfields layout; save it with 8 or 16 bits\)$"):
        read_image(path)


# ---- round 28 (A), H2, H3: map folders ------------------------------------------------------
def test_a_map_without_frame_names_is_refused(small_map, tmp_path):
    """H2: a map whose metadata lacks `frame_names` was loaded with no names against its
    training poses: pseudo-label crashed (IndexError), export wrote files that disagree."""
    import json
    import shutil

    bad = tmp_path / "nonames"
    shutil.copytree(small_map.root, bad)
    meta = json.loads((bad / "slamreloc_map.json").read_text())
    del meta["frame_names"]
    (bad / "slamreloc_map.json").write_text(json.dumps(meta, indent=1))
    code, err = run_cli(["export", str(bad), "--tum", str(tmp_path / "t.txt")])
    assert code == 2 and err.strip().splitlines()[-1] == (
        f"error: {bad / 'slamreloc_map.json'}: missing key 'frame_names'"), err
    assert not (tmp_path / "t.txt").exists()


@pytest.mark.parametrize("kind", ["named pipe", "folder"])
def test_a_map_file_that_is_no_file_is_named_as_such(small_map, tmp_path, kind):
    """H3: an output map whose regressor.npz is a named pipe or a folder was refused as
    holding something "which is not a map's"; the name is a map's, its kind is not."""
    import os
    import shutil

    out = tmp_path / "m"
    shutil.copytree(small_map.root, out)
    (out / "regressor.npz").unlink()
    os.mkfifo(out / "regressor.npz") if kind == "named pipe" else (out / "regressor.npz").mkdir()
    before = sorted(p.name for p in out.iterdir())
    from slamreloc.map.write import check_map_target

    with pytest.raises(InputError) as err:
        check_map_target(out)
    assert str(err.value) == (f"{out}: its 'regressor.npz' is a {kind}, not a map writer's "
                              "file; refusing to replace it (give the map's own folder, or "
                              "move it out)")
    assert sorted(p.name for p in out.iterdir()) == before


@pytest.mark.parametrize("camera", [(94, 48, 100, 70.5, 24), (320, 240, 262, 5.5, 120),
                                    (320, 240, 262, -100.0, 300.0)])
def test_a_cropped_barrel_lens_is_taken(camera):
    """A mild barrel lens (k1 = -0.03) with its principal point at or outside the circle
    inscribed in the image (a crop): its rays' distorted radius peaks far outside the image
    and turns back through the principal point, across the circle. That branch is no
    direction undistortion takes; the lens was refused as folding back (round 27's circle)."""
    width, height, f, cx, cy = camera
    assert fold_problem("OPENCV", (-0.03, 0.0, 0.0, 0.0), width, height, f, f, cx, cy) is None
