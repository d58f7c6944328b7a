"""Decoding images and depth maps from untrusted bytes, within the bounds of `slamreloc.io.limits`.

Nothing reaches a decoder before its header has been read and checked: the encoded size, the
width x height against `max_image_pixels` (a 48 KB PNG can claim 20000 x 20000 pixels and ask
the decoder for 1.2 GB), the smallest usable side, a PNG's chunk structure and CRCs, a JPEG's
end marker and scan count. Formats: PNG and JPEG (headers parsed here), BMP, TIFF, WebP and
PNM (headers read by Pillow, which decodes nothing on open); anything else is refused. Every
error is an `InputError` naming the source (a file, or a request on the wire).
"""

from __future__ import annotations

import io
import math
import os
import re
import struct
import sys
import tempfile
import threading
import zlib
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import TypeVar

import cv2
import numpy as np

from slamreloc.errors import InputError
from slamreloc.io.fileio import open_regular, read_bytes, regular_size
from slamreloc.io.limits import bytes_text, limits, over_limit, pixels_text

T = TypeVar("T")
# libjpeg's warnings (jerror.h): those that mean the data is corrupt or cut short, and the
# benign rest (all are kept off the user's terminal while a JPEG decodes)
LIBJPEG_CORRUPT = ("Corrupt JPEG data", "Premature end of JPEG file",
                   "Inconsistent progression sequence", "Invalid SOS parameters")
LIBJPEG_WARNINGS = LIBJPEG_CORRUPT + ("Warning: ", "Unknown Adobe color transform code",
                                      "Application transferred too many scanlines")
_STDERR_LOCK = threading.Lock()
INVALID_DEPTH = (0, 65535)  # raw uint16 values that mean "no measurement"
MAX_DEPTH_M = 65.534  # the deepest depth kept (uint16 millimetres' largest measurement)
# raw depth units per metre taken (the wire's `units_per_metre`): from 1 / MAX_DEPTH_M (fewer
# would leave no raw value within MAX_DEPTH_M, so no depth at all) to a micrometre
DEPTH_UNITS_PER_METRE = (1 / MAX_DEPTH_M, 1e6)
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
JPEG_MAGIC = b"\xff\xd8"
# formats Pillow reads the header of and OpenCV decodes (Pillow's format name -> shown name)
OTHER_FORMATS = {"BMP": "BMP", "TIFF": "TIFF", "WEBP": "WebP", "PPM": "PNM"}
PILLOW_MODES = {"1": (1, 1), "L": (1, 8), "P": (3, 8), "RGB": (3, 8), "RGBA": (4, 8),
                "LA": (2, 8), "CMYK": (4, 8), "I;16": (1, 16), "I;16B": (1, 16),
                "I;16L": (1, 16), "I": (1, 32), "F": (1, 32)}


@dataclass(frozen=True)
class ImageHeader:
    """What an encoded image says of itself, before any pixel is decoded."""

    width: int
    height: int
    channels: int
    bits: int  # per sample
    format: str  # PNG, JPEG, BMP, TIFF, WebP, PNM
    # the sample value that means full intensity where the format says (a PNM's maxval, 1 to
    # 65535; OpenCV decodes the raw samples); None: the whole range of `bits`
    maxval: int | None = None


def _png_chunks(data: bytes, source, what: str, verify_crc: bool):
    """Yield (type, payload) of each PNG chunk; raise on any structural defect."""
    pos = len(PNG_MAGIC)
    while True:
        if pos + 8 > len(data):
            raise InputError(f"{source}: not a readable {what} (PNG truncated)")
        length, kind = struct.unpack(">I4s", data[pos:pos + 8])
        end = pos + 12 + length
        if end > len(data):
            raise InputError(f"{source}: not a readable {what} (PNG truncated)")
        payload = data[pos + 8:pos + 8 + length]
        if verify_crc and zlib.crc32(kind + payload) != struct.unpack(">I", data[end - 4:end])[0]:
            raise InputError(f"{source}: not a readable {what} (PNG chunk {kind!r} is corrupt)")
        yield kind, payload
        if kind == b"IEND":
            return
        pos = end


def _png_header(data: bytes, source, what: str) -> ImageHeader:
    if len(data) < 33 or data[12:16] != b"IHDR":
        raise InputError(f"{source}: not a readable {what} (PNG without a header)")
    width, height, bits, colour = struct.unpack(">IIBB", data[16:26])
    channels = {0: 1, 2: 3, 3: 3, 4: 2, 6: 4}.get(colour)
    if channels is None or bits not in (1, 2, 4, 8, 16):
        raise InputError(f"{source}: not a readable {what} (bad PNG header)")
    return ImageHeader(width, height, channels, bits, "PNG")


def _jpeg_scan_end(data: bytes, start: int) -> int:
    """Where the entropy-coded data that starts at `start` ends: the position of the next
    marker that is not a stuffed 0xFF (FF 00) or a restart marker (RSTn), len(data) if none."""
    n, j = len(data), start
    while True:
        j = data.find(b"\xff", j)
        if j < 0 or j + 1 >= n:
            return n
        if data[j + 1] != 0x00 and not 0xD0 <= data[j + 1] <= 0xD7:
            return j
        j += 2


def _jpeg_segments(data: bytes) -> Iterator[tuple[int, int, int | None]]:
    """(marker, position, length field) of a JPEG's markers from SOI, walked by their lengths
    (None for the markers without one) and past each scan's entropy-coded data (SOS); ends
    after EOI, at a byte that is not a marker where one must be, a length field cut off, or a
    length under 2 (after yielding that marker)."""
    pos, n = 2, len(data)
    while pos + 1 < n:
        if data[pos] != 0xFF:
            return
        marker = data[pos + 1]
        if marker == 0xFF:  # fill byte
            pos += 1
            continue
        if marker in (0xD8, 0xD9, 0x01) or 0xD0 <= marker <= 0xD7:
            yield marker, pos, None
            if marker == 0xD9:  # EOI: what follows is not the image's
                return
            pos += 2
            continue
        if pos + 4 > n:
            return
        length = struct.unpack(">H", data[pos + 2:pos + 4])[0]
        yield marker, pos, length
        if length < 2:
            return
        pos += 2 + length
        if marker == 0xDA:  # SOS: its entropy-coded data runs to the next marker
            pos = _jpeg_scan_end(data, min(pos, n))


def jpeg_structure_problem(data: bytes) -> str | None:
    """Why a JPEG's bytes are not a complete stream (its markers walked from SOI by their
    lengths and past each scan's data): a bad segment length, a scan without entropy-coded
    data, or no end marker (EOI) after the scans; None for a complete one. Bytes after EOI
    are not the image's and are ignored (as after a PNG's IEND)."""
    scans = 0
    for marker, pos, length in _jpeg_segments(data):
        if length is not None and length < 2:
            return f"JPEG corrupt: a segment length of {length} at byte {pos}"
        if marker == 0xDA:
            start = pos + 2 + length
            if _jpeg_scan_end(data, min(start, len(data))) <= start:
                return "JPEG without scan data: the picture itself is missing"
            scans += 1
            if scans > limits().max_jpeg_scans:
                return f"JPEG with more than {limits().max_jpeg_scans} scans, " + over_limit(
                    "max_jpeg_scans")
        elif marker == 0xD9:
            return None if scans else "JPEG without scan data: the picture itself is missing"
    return "JPEG truncated or corrupt: no end marker after its scans"


def _jpeg_header(data: bytes, source, what: str) -> ImageHeader:
    for marker, pos, _ in _jpeg_segments(data):
        if marker == 0xDA:  # a scan before any frame header
            break
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):
            if pos + 10 > len(data):
                break
            bits, height, width, channels = struct.unpack(">BHHB", data[pos + 4:pos + 10])
            if channels not in (1, 3, 4):
                break
            return ImageHeader(width, height, channels, bits, "JPEG")
    raise InputError(f"{source}: not a readable {what} (no JPEG frame header found)")


_PILLOW_BOUND = threading.Lock()  # held while Pillow's own size bound is lifted
# the first bytes of the formats read through Pillow, to name one it cannot parse
_MAGIC = ((b"II*\0", "TIFF"), (b"MM\0*", "TIFF"), (b"PF", "PFM (PNM)"), (b"Pf", "PFM (PNM)"),
          (b"BM", "BMP"), *((f"P{k}".encode(), "PNM") for k in range(1, 8)))
# a PNM token after blanks and comments (a '#' starts a comment anywhere, even glued to a token)
_PNM_TOKEN = re.compile(rb"(?:\s|#[^\r\n]*)*([^\s#]+)")


def _pnm_header_tokens(data: bytes, n: int) -> tuple[list[bytes], int] | None:
    """The first `n` header tokens after a PNM's magic (width, height[, maxval]) and the
    offset just past them; None where the header holds fewer (Pillow's parse refuses it)."""
    tokens, pos = [], 2
    while len(tokens) < n:
        match = _PNM_TOKEN.match(data, pos, min(len(data), pos + 4096))
        if match is None:
            return None
        tokens.append(match.group(1))
        pos = match.end()
    return tokens, pos


def _pnm_pixels_text(data: bytes, after: int) -> bytes:
    """A plain PNM's pixel text from offset `after` (past its header), comments blanked."""
    return re.sub(rb"#[^\r\n]*", b" ", data[after:])


_PLAIN_PNM_BYTES = np.zeros(256, bool)  # what a plain PNM's samples are written with
_PLAIN_PNM_BYTES[list(b"0123456789 \t\n\v\f\r")] = True


def _plain_bitmap_problem(data: bytes) -> str | None:
    """Why a plain PBM's (P1) pixels are not its format's (None when they are): each is the
    digit 0 or 1 (whitespace between them optional), comments aside."""
    head = _pnm_header_tokens(data, 2)  # width, height
    if head is None:
        return None
    body = np.frombuffer(_pnm_pixels_text(data, head[1]), np.uint8)
    odd = np.flatnonzero(~_PLAIN_PNM_BYTES[body] | ((body >= ord("2")) & (body <= ord("9"))))
    return None if not len(odd) else (f"a plain PBM holds {bytes(body[odd[0]:odd[0] + 1])!r} "
                                      "among its pixels, which are 0 or 1")


def _ascii_pnm(data: bytes, header: ImageHeader, source, what: str) -> np.ndarray:
    """The raw samples of a plain (ASCII) PNM, P2 grey (H, W) or P3 colour (H, W, 3) in BGR
    order as OpenCV gives colour, uint8 for a maxval under 256, else uint16: OpenCV scales
    such samples to 255 and clamps those over the maxval, so it reads neither as the file
    holds them. A sample over the maxval, a missing or extra one, or a token that is no
    number is an InputError."""
    body = _pnm_pixels_text(data, _pnm_header_tokens(data, 3)[1])  # past width, height, maxval
    channels = 3 if data[:2] == b"P3" else 1
    count = header.width * header.height * channels
    odd = np.flatnonzero(~_PLAIN_PNM_BYTES[np.frombuffer(body, np.uint8)])
    if len(odd):  # a sign, a point, a letter...: no whole number in ASCII digits
        raise InputError(f"{source}: not a readable {what} (a plain PNM holds "
                         f"{body[odd[0]:odd[0] + 1]!r} among its samples, which are whole "
                         "numbers in ASCII digits)")
    # parsed in C, one int64 per sample (a sample of more digits than int64 holds reads as
    # its largest value: over any maxval)
    samples = np.fromstring(body, dtype=np.int64, sep=" ") if body.strip() else \
        np.zeros(0, np.int64)
    if len(samples) != count:
        raise InputError(f"{source}: not a readable {what} (a plain PNM of {len(samples)} "
                         f"samples, its header says {count})")
    if samples.max(initial=0) > header.maxval:
        top = int(samples.max())
        raise InputError(f"{source}: not a readable {what} (a PNM sample of "
                         f"{'19 or more digits' if top == np.iinfo(np.int64).max else top} is "
                         f"over the maxval {header.maxval} its header declares)")
    image = samples.astype(np.uint8 if header.maxval < 256 else np.uint16)
    image = image.reshape(header.height, header.width, channels)
    return image[..., ::-1].copy() if channels == 3 else image[..., 0]


def _pillow_pixels(data: bytes, colour: bool) -> np.ndarray:
    """A BMP decoded by Pillow, which reads every BMP layout its header parse takes (bit
    fields, V4/V5 headers) where OpenCV ignores the fields' masks: BGR uint8 (H, W, 3), or
    grey (H, W)."""
    from PIL import Image

    with _pillow_unbounded():  # the size is checked at open; decoding needs no lock
        img = Image.open(io.BytesIO(data))
    with img:
        if colour:
            return np.asarray(img.convert("RGB"))[..., ::-1].copy()
        return np.asarray(img.convert("L"))


def _pnm_maxval(data: bytes) -> int | None:
    """The maxval of a PNM of grey or colour samples (P2, P3, P5, P6: the 4th header token),
    None for other PNMs (bitmaps, PFM) and where it is no number (Pillow's parse refuses
    those)."""
    if data[:2] not in (b"P2", b"P3", b"P5", b"P6"):
        return None
    head = _pnm_header_tokens(data, 3)
    return int(head[0][2]) if head is not None and head[0][2].isdigit() else None


@contextmanager
def _pillow_unbounded() -> Iterator[None]:
    """Pillow's own size bound (2 x MAX_IMAGE_PIXELS, refused before a size can be read)
    lifted while the block runs, one block at a time: every format's size meets
    `check_image_size`'s one bound (`max_image_pixels`), which a user may raise."""
    import warnings

    from PIL import Image

    with _PILLOW_BOUND, warnings.catch_warnings():
        warnings.simplefilter("ignore")  # DecompressionBombWarning: sizes are checked by us
        bound, Image.MAX_IMAGE_PIXELS = Image.MAX_IMAGE_PIXELS, None
        try:
            yield
        finally:
            Image.MAX_IMAGE_PIXELS = bound


def _pillow_header(data: bytes, source, what: str) -> ImageHeader:
    from PIL import Image

    try:
        with _pillow_unbounded():  # `max_image_pixels` is the one bound, checked below
            with Image.open(io.BytesIO(data)) as img:  # parses the header, decodes nothing
                fmt, (width, height), mode = img.format, img.size, img.mode
                pages = bool(getattr(img, "is_animated", False))  # a next page: one look
                tiff = _tiff_samples(img) if fmt == "TIFF" else None
                layout = _tiff_layout_problem(img) if fmt == "TIFF" else None
    except Exception as err:  # noqa: BLE001 - Pillow's parsers raise many kinds on bad bytes
        known = next((name for magic, name in _MAGIC if data.startswith(magic)), None)
        unknown = "cannot identify" in str(err)
        if known is not None:  # a format we read, in a layout or with samples we do not
            why = ("which its header reader cannot parse: e.g. float or 32-bit colour "
                   "samples, 16-bit grey with alpha, or a damaged header" if unknown else
                   f"{type(err).__name__}: {' '.join(str(err).split())[:80]}")
            raise InputError(f"{source}: not a readable {what} (a {known} whose layout or "
                             f"samples are not read, {why}; save it with 8 or 16 bits)"
                             ) from None
        kind = "unknown format" if unknown else type(err).__name__
        raise InputError(f"{source}: not a readable {what} ({kind}; PNG, JPEG, BMP, TIFF, "
                         "WebP and PNM are read)") from None
    if fmt not in OTHER_FORMATS:
        raise InputError(f"{source}: {fmt} is not a supported {what} format (PNG, JPEG, BMP, "
                         "TIFF, WebP and PNM are read)")
    if pages:  # which page was meant? (an animated GIF is refused by its format)
        raise InputError(f"{source}: a {OTHER_FORMATS[fmt]} {what} of more than one page or "
                         "frame; give one image per file")
    channels, bits = PILLOW_MODES.get(mode, (4, 8))
    if fmt == "PPM" and mode == "I":  # Pillow's mode for a PGM of 16-bit samples (maxval
        bits = 16                     # over 255): PNM holds no wider ones
    if layout is not None:
        raise InputError(f"{source}: not a readable {what} ({layout})")
    if fmt == "TIFF" and tiff is not None:  # the file's own samples, not Pillow's widened mode
        bits, sample_format = tiff
        if sample_format not in (None, 1):  # 2: signed, 3: floating point
            kind = {2: "signed", 3: "floating-point"}.get(sample_format, "other")
            raise InputError(f"{source}: not a readable {what} (a TIFF of {bits}-bit {kind} "
                             "samples; save it with unsigned 8 or 16 bits)")
    return ImageHeader(width, height, channels, bits, OTHER_FORMATS[fmt],
                       _pnm_maxval(data) if fmt == "PPM" else None)


def _tiff_layout_problem(img) -> str | None:
    """What of an open TIFF's layout OpenCV would read otherwise than the file says (None:
    nothing): an Orientation tag other than 1 (OpenCV rotates the pixels whatever it is
    told, while every other format's stored pixels are read as stored), and 16-bit samples of
    a MinIsWhite image (OpenCV does not invert them)."""
    tags = getattr(img, "tag_v2", {})
    if tags.get(274, 1) != 1:
        return (f"a TIFF whose Orientation tag ({tags.get(274)}) rotates its pixels; save it "
                "with its pixels as the camera took them (Orientation 1)")
    bits = tags.get(258)
    bits = max(bits) if isinstance(bits, tuple) else bits
    if tags.get(262) == 0 and bits == 16:
        return "a 16-bit MinIsWhite TIFF; save it MinIsBlack, or with 8 bits"
    return None


def _tiff_samples(img) -> tuple[int, int | None] | None:
    """(bits per sample, the SampleFormat tag: 1 unsigned, 2 signed, 3 floating point, None
    unsaid) of an open TIFF, from its tags; None where it gives no BitsPerSample."""
    tags = getattr(img, "tag_v2", {})
    bits = tags.get(258)
    if not bits:
        return None
    bits = max(bits) if isinstance(bits, tuple) else int(bits)
    formats = tags.get(339)
    sample_format = (max(formats) if isinstance(formats, tuple) else formats) if formats \
        else None
    return int(bits), None if sample_format is None else int(sample_format)


def encoded_header(data: bytes, source, what: str = "image") -> ImageHeader:
    """The header of an encoded image (PNG, JPEG, BMP, TIFF, WebP, PNM), checked against the
    bounds; decodes nothing. `source` names the file or request in errors."""
    if len(data) == 0:
        raise InputError(f"{source}: not a readable {what} (empty or corrupt: 0 bytes)")
    if data.startswith(PNG_MAGIC):
        header = _png_header(data, source, what)
    elif data.startswith(JPEG_MAGIC):
        header = _jpeg_header(data, source, what)
    else:
        header = _pillow_header(data, source, what)
    check_image_size(header.width, header.height, source, what)
    return header


def check_image_size(width: int, height: int, source, what: str = "image") -> None:
    """InputError unless width x height is within `min_image_side` and `max_image_pixels`."""
    lim = limits()
    if min(width, height) < lim.min_image_side:
        raise InputError(f"{source}: {what} is {width}x{height} pixels; at least "
                         f"{lim.min_image_side} pixels a side are needed")
    if width * height > lim.max_image_pixels:
        raise InputError(f"{source}: {what} is {width}x{height} = " + over_limit(
            "max_image_pixels", pixels_text(width * height)))


def jpeg_has_scan_data(data: bytes) -> bool:
    """Whether a JPEG's first scan (SOS) is followed by entropy-coded bytes (its markers
    walked from SOI by their lengths up to it)."""
    for marker, pos, length in _jpeg_segments(data):
        if marker == 0xD9 or (length is not None and length < 2):  # EOI before a scan; bad
            return False
        if marker == 0xDA:
            start = pos + 2 + length
            end = _jpeg_scan_end(data, min(start, len(data)))
            return start < end < len(data)
    return False


def check_encoded_image(data: bytes, source, what: str = "image") -> ImageHeader:
    """The checked header of a complete encoded image: refuse an empty, truncated, (PNG)
    corrupted, oversized or (JPEG) over-scanned one."""
    lim = limits()
    if len(data) > lim.max_image_bytes:
        raise InputError(f"{source}: encoded {what} of " + over_limit(
            "max_image_bytes", bytes_text(len(data))))
    header = encoded_header(data, source, what)
    if header.format == "PNG":
        for _ in _png_chunks(data, source, what, verify_crc=True):
            pass
    elif header.format == "JPEG":
        problem = jpeg_structure_problem(data)
        if problem:
            raise InputError(f"{source}: not a readable {what} ({problem})")
    return header


def _opencv_tiff_line(line: str) -> bool:
    """Whether a line OpenCV logged is about the TIFF it decodes (libtiff's errors, its own)."""
    return line.startswith(("[ERROR", "[ WARN")) and ("grfmt_tiff" in line or "imdecode_" in line)


def _tiff_problem(lines: list[str]) -> str | None:
    """The first problem OpenCV logged while decoding a TIFF (libtiff's `TIFF_Error ...`, or
    the reason it could not read the header or data), for a message; None where it logged
    none."""
    for line in lines:
        text = line.split("TIFF_Error ", 1)[1] if "TIFF_Error " in line else \
            line.split("error: (-2:Unspecified error) ", 1)[1].split(" in function")[0] \
            if "error: (-2:Unspecified error) " in line else None
        if text:
            return " ".join(text.split()).rstrip(".")[:120]
    return None


def _with_native_stderr(decode: Callable[[], T],
                        mine: Callable[[str], bool] | None = None) -> tuple[T, list[str]]:
    """(`decode()`, the lines native code wrote to stderr meanwhile): libjpeg says that a JPEG
    is corrupt or cut short only there (a warning, after which it returns a picture padded with
    grey). File descriptor 2 goes to a memory file for the call, one call at a time (a lock);
    what other threads wrote meanwhile, not a libjpeg warning, is written back to stderr."""
    with _STDERR_LOCK:
        try:
            sys.stderr.flush()
        except (OSError, ValueError):
            pass
        if hasattr(os, "memfd_create"):
            capture = os.memfd_create("slamreloc-stderr")
        else:
            capture, name = tempfile.mkstemp()
            os.unlink(name)
        saved = os.dup(2)
        try:
            os.dup2(capture, 2)
            try:
                result = decode()
            finally:
                os.dup2(saved, 2)
            os.lseek(capture, 0, os.SEEK_SET)
            chunks = []
            while chunk := os.read(capture, 1 << 16):
                chunks.append(chunk)
        finally:
            os.close(saved)
            os.close(capture)
    lines = b"".join(chunks).decode("utf-8", "replace").splitlines()
    mine = mine or (lambda line: line.startswith(LIBJPEG_WARNINGS))
    ours = [line for line in lines if mine(line)]
    others = [line for line in lines if not mine(line)]
    if others:
        os.write(2, ("\n".join(others) + "\n").encode())
    return result, ours


def decode_image(data: bytes, source, flags: int = cv2.IMREAD_COLOR, what: str = "image",
                 fits: Callable[[int, int, object], None] | None = None) -> np.ndarray:
    """Decode checked bytes with OpenCV (`flags` as cv2.imdecode's); the array as decoded
    (BGR for colour), raw samples (a PNM's are not scaled by its maxval: depth maps hold
    units, not intensities). `fits(width, height, source)`: a further check of the header's
    size before decoding (a feature extractor's `check_size`)."""
    return _decode(data, source, flags, what, fits)[0]


def _decode(data: bytes, source, flags: int, what: str,
            fits: Callable[[int, int, object], None] | None) -> tuple[np.ndarray, ImageHeader]:
    """decode_image's array, and the header it was checked by. A PNM sample over the maxval
    its header declares is an InputError: the file breaks its own format."""
    header = check_encoded_image(data, source, what)
    if header.bits > 16:  # OpenCV decodes none, or casts them to 8 bits (a float PFM: 0 or 1)
        raise InputError(f"{source}: not a readable {what} ({header.bits}-bit "
                         f"{header.format} samples, which OpenCV does not decode; save it "
                         "with 8 or 16 bits)")
    if fits is not None:
        fits(header.width, header.height, source)
    # the pixels as stored: a JPEG's EXIF orientation is not applied (its header's size is
    # the decoded one; a camera's intrinsics describe the sensor, not a rotated picture)
    flags |= cv2.IMREAD_IGNORE_ORIENTATION
    if header.format == "JPEG":
        img, warnings = _with_native_stderr(lambda: cv2.imdecode(np.frombuffer(data, np.uint8),
                                                                flags))
        warning = next((w for w in warnings if w.startswith(LIBJPEG_CORRUPT)), None)
        if warning is not None:
            reason = warning.removeprefix("Corrupt JPEG data: ").rstrip(".")
            raise InputError(f"{source}: not a readable {what} (JPEG corrupt or truncated: "
                             f"{reason[:80]})")
    elif header.format == "PNM" and data[:2] in (b"P2", b"P3") and header.maxval:
        img = _ascii_pnm(data, header, source, what)
        colour = flags > 0 and flags & cv2.IMREAD_COLOR
        if colour and img.ndim == 2:
            img = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
        elif not colour and img.ndim == 3:
            img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    elif header.format == "PNM" and data[:2] == b"P1" and \
            (problem := _plain_bitmap_problem(data)) is not None:
        raise InputError(f"{source}: not a readable {what} ({problem})")
    elif header.format == "TIFF":  # libtiff says a file is cut short only in OpenCV's log
        img, logged = _with_native_stderr(
            lambda: cv2.imdecode(np.frombuffer(data, np.uint8), flags), _opencv_tiff_line)
        problem = _tiff_problem(logged)
        if problem is not None:
            raise InputError(f"{source}: not a readable {what} (TIFF: {problem})")
    elif header.format == "BMP":
        try:
            img = _pillow_pixels(data, bool(flags > 0 and flags & cv2.IMREAD_COLOR))
        except Exception as err:  # noqa: BLE001 - cut short or damaged pixel data
            raise InputError(f"{source}: not a readable {what} (BMP pixel data: "
                             f"{type(err).__name__}: {' '.join(str(err).split())[:80]})"
                             ) from None
    else:
        img = cv2.imdecode(np.frombuffer(data, np.uint8), flags)
    if img is None or img.size == 0:
        raise InputError(f"{source}: not a readable {what} (empty or corrupt)")
    if (img.shape[1], img.shape[0]) != (header.width, header.height):
        raise InputError(f"{source}: not a readable {what} (decoded {img.shape[1]}x"
                         f"{img.shape[0]}, its header says {header.width}x{header.height})")
    if header.maxval is not None and int(img.max()) > header.maxval:
        raise InputError(f"{source}: not a readable {what} (a PNM sample of {int(img.max())} "
                         f"is over the maxval {header.maxval} its header declares)")
    return img, header


def decode_rgb(data: bytes, source,
               fits: Callable[[int, int, object], None] | None = None) -> np.ndarray:
    """RGB uint8 (H, W, 3) from encoded bytes: samples scaled so that full intensity is 255
    (a 16-bit image's 65535, a PNM's maxval, as the format defines them); `fits` as
    decode_image's."""
    img, header = _decode(data, source, cv2.IMREAD_COLOR | cv2.IMREAD_ANYDEPTH, "image", fits)
    full = header.maxval or (255 if img.dtype == np.uint8 else 65535)
    if img.dtype != np.uint8 or full != 255:
        img = cv2.convertScaleAbs(img, alpha=255.0 / full)
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def picture_digest(image: np.ndarray) -> str:
    """SHA-256 (hex) of an image's pixels as the readers decode them (`decode_rgb`'s RGB
    uint8, with its shape): one picture, whatever file, format or bytes it came in, whether
    read from a file or received over the wire. A lossless re-encoding, a file with trailing
    bytes or other metadata gives the same digest; a lossy re-encoding does not."""
    import hashlib

    pixels = np.ascontiguousarray(image)
    digest = hashlib.sha256(f"{pixels.dtype.str}{pixels.shape}".encode())
    digest.update(memoryview(pixels).cast("B"))
    return digest.hexdigest()


def encode_image(pixels: np.ndarray, suffix: str, source, params: tuple[int, ...] = ()
                 ) -> bytes:
    """The file bytes of `pixels` (OpenCV's order: BGR, or one channel; uint8 or uint16) in
    the format of `suffix` (".png", ".jpg"); InputError naming `source` where OpenCV cannot
    encode them."""
    ok, data = cv2.imencode(suffix, pixels, list(params))
    if not ok:
        raise InputError(f"{source}: cannot encode the image as {suffix.lstrip('.').upper()}")
    return data.tobytes()


def write_image(path: str | Path, pixels: np.ndarray, params: tuple[int, ...] = ()) -> None:
    """Write `pixels` (as `encode_image`) to `path`, in the format of its suffix, through
    Python's file API: a path OpenCV's own writer cannot take (a name that is not UTF-8 text)
    is written all the same."""
    Path(path).write_bytes(encode_image(pixels, Path(path).suffix, path, params))


def pixel_colours(image: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """(N, C) values of `image` at the pixels nearest to `xy` (N, 2; x right, y down; clipped
    to the image)."""
    h, w = image.shape[:2]
    uv = np.round(np.asarray(xy, np.float64)).astype(np.int64)
    return image[np.clip(uv[:, 1], 0, h - 1), np.clip(uv[:, 0], 0, w - 1)]


def _file_bytes(path: Path, what: str) -> bytes:
    return read_bytes(path, what, "max_image_bytes")


def size_problem(got: tuple[int, int], size: tuple[int, int], what: str = "image"
                 ) -> str | None:
    """Why an image (or, `what` "depth", a registered depth map) of `got` (width, height)
    pixels is not of its dataset's `size`; None when it is. The one rule of a frame's size,
    at the dataset's load (`check_frame_files`) and where each file is read."""
    if tuple(got) == tuple(size):
        return None
    if what == "depth":
        return (f"depth is {got[0]}x{got[1]}, its image is {size[0]}x{size[1]} (registered "
                "depth must match)")
    return f"image is {got[0]}x{got[1]}, the dataset's images are {size[0]}x{size[1]}"


def read_image(path: str | Path, fits: Callable[[int, int, object], None] | None = None,
               size: tuple[int, int] | None = None) -> np.ndarray:
    """RGB uint8 (H, W, 3) from an image file; `fits` as decode_image's. `size` (width,
    height): the size the image must have (`size_problem`)."""
    image = decode_rgb(_file_bytes(Path(path), "image"), Path(path), fits)
    problem = size and size_problem((image.shape[1], image.shape[0]), size)
    if problem:
        raise InputError(f"{path}: {problem}")
    return image


def read_depth(path: str | Path, units_per_metre: float = 1000.0,
               size: tuple[int, int] | None = None) -> np.ndarray:
    """float32 depth in metres (H, W) from a 16-bit single-channel image; invalid pixels (raw
    0 or 65535) are 0. `size` (width, height): the size the depth must have."""
    path = Path(path)
    raw = decode_image(_file_bytes(path, "depth"), path, cv2.IMREAD_ANYDEPTH, "depth")
    if raw.ndim != 2:
        raise InputError(f"{path}: depth must be a single-channel image, got shape {raw.shape}")
    if raw.dtype != np.uint16:
        raise InputError(f"{path}: depth must be 16-bit (uint16), got {raw.dtype}")
    problem = size and size_problem((raw.shape[1], raw.shape[0]), size, "depth")
    if problem:
        raise InputError(f"{path}: {problem}")
    return depth_from_raw(raw, units_per_metre)


def depth_from_raw(raw: np.ndarray, units_per_metre: float) -> np.ndarray:
    """float32 metres from raw uint16 depth: raw 0 and 65535 mean "no measurement" (0), as
    in every reader (depth files, the service's UINT16 and PNG16 depth, ROS bags), and so
    does a depth beyond MAX_DEPTH_M once scaled (float depth's rule, `clean_depth_m`)."""
    depth = raw.astype(np.float32) / units_per_metre
    depth[np.isin(raw, INVALID_DEPTH) | (depth > MAX_DEPTH_M)] = 0.0
    return depth


def depth_units_problem(units: float) -> str | None:
    """Why `units` cannot be raw depth units per metre (None when it can): the one rule of
    `DEPTH_UNITS_PER_METRE`, for a frame's depth and a session's default alike."""
    low, high = DEPTH_UNITS_PER_METRE
    if not (math.isfinite(units) and low <= units <= high):
        return (f"must be in [{low:.4f}, {high:g}] (fewer units per metre leave no raw value "
                f"within {MAX_DEPTH_M} m), got {units:g}")
    return None


def clean_depth_m(depth: np.ndarray) -> np.ndarray:
    """float depth in metres with every value that is no measurement set to 0, in place: NaN,
    +-inf (REP 118's too near / too far), 0 or negative, and beyond MAX_DEPTH_M. The one rule
    of float depth (the service's FLOAT32_METRES, a ROS bag's 32FC1)."""
    depth[~np.isfinite(depth) | (depth <= 0) | (depth > MAX_DEPTH_M)] = 0.0
    return depth


def image_header(path: str | Path, what: str = "image") -> ImageHeader:
    """The checked header of an image file, reading as little of it as the format allows."""
    path = Path(path)
    try:
        with open_regular(path, what) as f:
            head = f.read(1 << 16)
            rest = f.peek(1) if hasattr(f, "peek") else b""
            if head.startswith(PNG_MAGIC) or not rest:
                return encoded_header(head, path, what)
            if head.startswith(JPEG_MAGIC):
                try:  # the frame header is near the start unless large EXIF blocks precede it
                    return encoded_header(head, path, what)
                except InputError:
                    pass
            size = regular_size(f)  # other formats' parsers want the whole file (bounded)
            if size > limits().max_image_bytes:
                raise InputError(f"{path}: encoded {what} of " + over_limit(
                    "max_image_bytes", bytes_text(size)))
            head += f.read(size)  # (a buffer of its size, not of the bound, which may be huge)
    except OSError as err:
        raise InputError(f"{path}: cannot read {what} ({err.strerror or err})") from None
    return encoded_header(head, path, what)


def image_size(path: str | Path) -> tuple[int, int]:
    """(width, height) of an image, from its header."""
    header = image_header(path)
    return header.width, header.height


def check_frame_files(image_path: Path, size: tuple[int, int], depth_path: Path | None = None,
                      check_depth: bool = False) -> None:
    """At dataset load: the image has the dataset's size; registered depth (if asked) is a
    16-bit single-channel image of the same size. Reads headers only."""
    problem = size_problem(image_size(image_path), size)
    if problem:
        raise InputError(f"{image_path}: {problem}")
    if check_depth and depth_path is not None:
        h = image_header(depth_path, "depth")
        if h.channels != 1 or h.bits != 16:
            raise InputError(f"{depth_path}: depth must be a 16-bit single-channel image, got "
                             f"{h.channels} channel(s) of {h.bits} bits")
        problem = size_problem((h.width, h.height), size, "depth")
        if problem:
            raise InputError(f"{depth_path}: {problem}")
