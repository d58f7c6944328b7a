"""Attack round 30: around round 29's image fixes.
M1, M6: a plain PNM was parsed word by word in Python (3.9 GB for a 4096x4096 P3 within the
bounds; a 20-digit sample a traceback). M7: a plain PBM's pixels other than 0 and 1 taken.
M2: a TIFF's Orientation tag rotated the pixels (OpenCV applies it whatever it is told).
M3, M5: a TIFF OpenCV cannot decode, or one cut short (libtiff says so only in a log line),
was "empty or corrupt", or taken with a plane of zeros. M8: a 16-bit MinIsWhite TIFF read as
its negative."""
from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest

from slamreloc.errors import InputError
from slamreloc.io.images import read_image


# ---- M1, M6, M7: plain PNMs -----------------------------------------------------------------
@pytest.mark.parametrize("body, problem", [
    ("1 2 -3", r"a plain PNM holds b'-' among its samples, which are whole numbers in ASCII digits"),
    ("1 2.5 3", r"a plain PNM holds b'\.' among its samples"),
    ("1 2 3 4", r"a plain PNM of 4 samples, its header says 3"),
    ("1 2 99999999999999999999", r"a PNM sample of 19 or more digits is over the maxval 255"),
])
def test_a_plain_pnm_that_breaks_its_format_is_one_error(tmp_path, body, problem):
    path = tmp_path / "p.pgm"
    path.write_text(f"P2\n3 1\n255\n{body}\n")
    from slamreloc.io import limits

    bounds = limits.limits()
    limits.set_limits(min_image_side=1)
    try:
        with pytest.raises(InputError, match=r"p\.pgm: not a readable image \(" + problem):
            read_image(path)
    finally:
        limits.use_limits(bounds)


def test_a_plain_pbm_holds_only_zeros_and_ones(tmp_path):
    pixels = np.random.default_rng(1).integers(0, 2, (16, 24))
    rows = "\n".join("".join(map(str, r)) for r in pixels)  # no blanks between pixels: valid
    (tmp_path / "ok.pbm").write_text(f"P1\n24 16\n{rows}\n")
    image = read_image(tmp_path / "ok.pbm")
    assert np.array_equal(image[..., 0] == 0, pixels == 1)  # 1 is black
    (tmp_path / "bad.pbm").write_text(f"P1\n24 16\n{rows[:-1]}7\n")
    with pytest.raises(InputError, match=r"bad\.pbm: not a readable image \(a plain PBM holds "
                                         r"b'7' among its pixels, which are 0 or 1\)"):
        read_image(tmp_path / "bad.pbm")


# ---- M2, M3, M5, M8: TIFFs ------------------------------------------------------------------
def _tiff(path: Path, width: int, height: int, planes: list[bytes], bits: int, spp: int,
          photometric: int, orientation: int = 1) -> Path:
    """An uncompressed little-endian TIFF: `planes` one strip each (one plane, or one per
    sample with PlanarConfiguration 2); each strip's byte count as the image needs, whatever
    the bytes given (a cut one is short)."""
    per_plane = len(planes) > 1
    row_bits = width * bits * (1 if per_plane else spp)
    strip = (row_bits + 7) // 8 * height
    tags = {256: (4, [width]), 257: (4, [height]), 258: (3, [bits] * spp), 259: (3, [1]),
            262: (3, [photometric]), 274: (3, [orientation]), 277: (3, [spp]),
            278: (4, [height]), 279: (4, [strip] * len(planes)), 284: (3, [2 if per_plane else 1])}
    n = len(tags) + 1  # + StripOffsets
    ifd_size = 2 + 12 * n + 4
    extra, extra_at = b"", 8 + ifd_size
    data_at = extra_at + 64
    offsets, pos = [], data_at
    for plane in planes:
        offsets.append(pos)
        pos += len(plane)
    tags[273] = (4, offsets)
    entries = b""
    for tag in sorted(tags):
        kind, values = tags[tag]
        size = {3: 2, 4: 4}[kind]
        packed = struct.pack(f"<{len(values)}{'H' if kind == 3 else 'I'}", *values)
        if len(packed) <= 4:
            entries += struct.pack("<HHI", tag, kind, len(values)) + packed.ljust(4, b"\0")
        else:
            entries += struct.pack("<HHII", tag, kind, len(values), extra_at + len(extra))
            extra += packed
        assert size * len(values) == len(packed)
    head = b"II*\0" + struct.pack("<I", 8) + struct.pack("<H", n) + entries + bytes(4)
    path.write_bytes(head + extra.ljust(64, b"\0") + b"".join(planes))
    return path


RGB = np.random.default_rng(0).integers(0, 256, (48, 64, 3), dtype=np.uint8)


def test_tiffs_read_as_stored(tmp_path):
    """The writer above makes TIFFs the reader takes: chunky and planar RGB, 8-bit grey."""
    chunky = _tiff(tmp_path / "c.tif", 64, 48, [RGB.tobytes()], 8, 3, 2)
    planar = _tiff(tmp_path / "p.tif", 64, 48, [RGB[..., k].tobytes() for k in range(3)], 8,
                   3, 2)
    assert np.array_equal(read_image(chunky), RGB) and np.array_equal(read_image(planar), RGB)


def test_a_rotating_orientation_tag_is_refused(tmp_path):
    path = _tiff(tmp_path / "o.tif", 64, 48, [RGB.tobytes()], 8, 3, 2, orientation=6)
    with pytest.raises(InputError, match=r"o\.tif: not a readable image \(a TIFF whose "
                                         r"Orientation tag \(6\) rotates its pixels"):
        read_image(path)


def test_a_tiff_opencv_cannot_decode_says_why(tmp_path):
    grey4 = np.random.default_rng(2).integers(0, 16, (48, 64), dtype=np.uint8)
    packed = (grey4[:, 0::2] << 4 | grey4[:, 1::2]).astype(np.uint8).tobytes()
    path = _tiff(tmp_path / "g.tif", 64, 48, [packed], 4, 1, 1)
    with pytest.raises(InputError, match=r"g\.tif: not a readable image \(TIFF: .*4"):
        read_image(path)


def test_a_planar_tiff_cut_short_is_refused(tmp_path):
    planes = [RGB[..., 0].tobytes(), RGB[..., 1].tobytes()[:-1000]]  # blue plane missing
    path = _tiff(tmp_path / "cut.tif", 64, 48, planes + [b""], 8, 3, 2)
    with pytest.raises(InputError, match=r"cut\.tif: not a readable image \(TIFF: "):
        read_image(path)


def test_a_16_bit_min_is_white_tiff_is_refused(tmp_path):
    grey = np.random.default_rng(3).integers(0, 65536, (48, 64)).astype("<u2")
    path = _tiff(tmp_path / "w.tif", 64, 48, [grey.tobytes()], 16, 1, 0)
    with pytest.raises(InputError, match=r"w\.tif: not a readable image \(a 16-bit MinIsWhite "
                                         r"TIFF; save it MinIsBlack, or with 8 bits\)"):
        read_image(path)
