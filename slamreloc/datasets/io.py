"""Reading images, depth maps, poses and intrinsics, with one-line errors naming the file.

Files are checked before a decoder sees them: a PNG must be complete with every chunk's CRC
right, a JPEG must start with SOI and end with EOI, so a truncated or bit-flipped file is an
`InputError` instead of a warning from the C library and a half-decoded image.
"""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import cv2
import numpy as np

from slamreloc.errors import InputError
from slamreloc.geometry import Rigid3

INVALID_DEPTH = (0, 65535)  # raw uint16 values that mean "no measurement"
MAX_IMAGE_BYTES = 1 << 30
MAX_TEXT_BYTES = 1 << 20  # a pose or an intrinsics matrix
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def _read_bytes(path: Path, what: str, limit: int) -> bytes:
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: {what} file not found")
    try:
        size = path.stat().st_size
        if size > limit:
            raise InputError(f"{path}: {size} bytes, too large for a {what} file")
        return path.read_bytes()
    except OSError as err:
        raise InputError(f"{path}: cannot read {what} ({err.strerror or err})") from None


def _png_chunks(data: bytes, path: Path, what: str, verify_crc: bool):
    """Yield (type, payload) of each PNG chunk; raise on any structural defect."""
    pos = len(PNG_MAGIC)
    while True:
        if pos + 8 > len(data):
            raise InputError(f"{path}: not a readable {what} (PNG truncated)")
        length, kind = struct.unpack(">I4s", data[pos:pos + 8])
        end = pos + 12 + length
        if end > len(data):
            raise InputError(f"{path}: not a readable {what} (PNG truncated)")
        payload = data[pos + 8:pos + 8 + length]
        if verify_crc and zlib.crc32(kind + payload) != struct.unpack(">I", data[end - 4:end])[0]:
            raise InputError(f"{path}: not a readable {what} (PNG chunk {kind!r} is corrupt)")
        yield kind, payload
        if kind == b"IEND":
            return
        pos = end


def check_encoded_image(data: bytes, path: Path, what: str = "image") -> None:
    """Refuse an empty, truncated or (PNG) corrupted encoded image."""
    if len(data) == 0:
        raise InputError(f"{path}: not a readable {what} (empty or corrupt: 0 bytes)")
    if data.startswith(PNG_MAGIC):
        for _ in _png_chunks(data, path, what, verify_crc=True):
            pass
    elif data.startswith(b"\xff\xd8"):
        if b"\xff\xd9" not in data[-64:]:
            raise InputError(f"{path}: not a readable {what} (JPEG truncated: no end marker)")


def _imread(path: Path, flags: int, what: str) -> np.ndarray:
    path = Path(path)
    data = _read_bytes(path, what, MAX_IMAGE_BYTES)
    check_encoded_image(data, path, what)
    img = cv2.imdecode(np.frombuffer(data, np.uint8), flags)
    if img is None or img.size == 0:
        raise InputError(f"{path}: not a readable {what} (empty or corrupt)")
    return img


def read_image(path: Path) -> np.ndarray:
    """RGB uint8 (H, W, 3)."""
    img = _imread(path, cv2.IMREAD_COLOR, "image")
    if img.dtype != np.uint8:
        img = cv2.convertScaleAbs(img, alpha=255.0 / 65535.0)
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def read_depth(path: Path, units_per_metre: float = 1000.0,
               size: tuple[int, int] | None = None) -> np.ndarray:
    """float32 depth in metres (H, W) from a 16-bit single-channel image; invalid pixels (raw
    0 or 65535) are 0. `size` (width, height): the size the depth must have."""
    raw = _imread(path, cv2.IMREAD_ANYDEPTH, "depth")
    if raw.ndim != 2:
        raise InputError(f"{path}: depth must be a single-channel image, got shape {raw.shape}")
    if raw.dtype != np.uint16:
        raise InputError(f"{path}: depth must be 16-bit (uint16), got {raw.dtype}")
    if size is not None and (raw.shape[1], raw.shape[0]) != tuple(size):
        raise InputError(f"{path}: depth is {raw.shape[1]}x{raw.shape[0]}, its image is "
                         f"{size[0]}x{size[1]}")
    depth = raw.astype(np.float32) / units_per_metre
    depth[np.isin(raw, INVALID_DEPTH)] = 0.0
    return depth


def read_text(path: Path, what: str, limit: int = 1 << 30) -> str:
    """A text file's contents; a binary or oversized file is an InputError naming it."""
    data = _read_bytes(path, what, limit)
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError:
        raise InputError(f"{path}: {what} is not a text file (not UTF-8)") from None


def _read_matrix(path: Path, what: str, shape: tuple[int, int]) -> np.ndarray:
    path = Path(path)
    text = read_text(path, what, MAX_TEXT_BYTES)
    rows = [line.split() for line in text.splitlines()
            if line.strip() and not line.lstrip().startswith("#")]
    if len({len(r) for r in rows}) > 1:
        raise InputError(f"{path}: {what} is not a numeric matrix (rows of different lengths)")
    try:
        m = np.array([[float(v) for v in row] for row in rows], dtype=np.float64)
    except ValueError as err:
        raise InputError(f"{path}: {what} is not a numeric matrix ({err})") from None
    m = m.reshape(len(rows), -1) if rows else np.zeros((0, 0))
    if m.shape != shape:
        raise InputError(f"{path}: {what} must be a {shape[0]}x{shape[1]} matrix, "
                         f"got shape {m.shape}")
    return m


def read_pose(path: Path) -> Rigid3:
    """A 4x4 camera-to-world matrix in metres (7-Scenes pose.txt) -> world_from_cam."""
    return Rigid3.from_matrix(_read_matrix(path, "pose", (4, 4)), source=str(path))


def write_pose(path: Path, world_from_cam: Rigid3) -> None:
    np.savetxt(path, world_from_cam.matrix(), fmt="%.9f")


def read_intrinsics(path: Path) -> np.ndarray:
    """A 3x3 K matrix; raises unless fx, fy > 0 and cx, cy >= 0."""
    k = _read_matrix(path, "intrinsics", (3, 3))
    if not np.all(np.isfinite(k)) or k[0, 0] <= 0 or k[1, 1] <= 0 or k[0, 2] < 0 or k[1, 2] < 0:
        raise InputError(f"{path}: intrinsics must have positive fx, fy and non-negative cx, cy")
    return k


def image_header(path: Path, what: str = "image") -> tuple[int, int, int, int]:
    """(width, height, channels, bits per sample) from a PNG or JPEG header, without decoding
    the pixels (other formats are decoded)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: {what} file not found")
    try:
        with open(path, "rb") as f:
            head = f.read(1 << 16)
    except OSError as err:
        raise InputError(f"{path}: cannot read {what} ({err.strerror or err})") from None
    if head.startswith(PNG_MAGIC):
        if len(head) < 33 or head[12:16] != b"IHDR":
            raise InputError(f"{path}: not a readable {what} (PNG without a header)")
        width, height, bits, colour = struct.unpack(">IIBB", head[16:26])
        channels = {0: 1, 2: 3, 3: 3, 4: 2, 6: 4}.get(colour)
        if channels is None or width == 0 or height == 0:
            raise InputError(f"{path}: not a readable {what} (bad PNG header)")
        return width, height, channels, bits
    if head.startswith(b"\xff\xd8"):
        return _jpeg_header(head, path, what)
    img = _imread(path, cv2.IMREAD_UNCHANGED, what)
    bits = 8 * img.dtype.itemsize
    return img.shape[1], img.shape[0], 1 if img.ndim == 2 else img.shape[2], bits


def _jpeg_header(head: bytes, path: Path, what: str) -> tuple[int, int, int, int]:
    pos = 2
    while pos + 4 <= len(head):
        if head[pos] != 0xFF:
            break
        marker = head[pos + 1]
        if marker == 0xFF:  # fill byte
            pos += 1
            continue
        if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:
            pos += 2
            continue
        length = struct.unpack(">H", head[pos + 2:pos + 4])[0]
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):
            if pos + 10 > len(head):
                break
            bits, height, width, channels = struct.unpack(">BHHB", head[pos + 4:pos + 10])
            if width == 0 or height == 0 or channels not in (1, 3, 4):
                break
            return width, height, channels, bits
        if length < 2:
            break
        pos += 2 + length
    raise InputError(f"{path}: not a readable {what} (no JPEG frame header found)")


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) of an image, reading only its header where it can."""
    width, height, _, _ = image_header(path)
    return width, height


def check_frame_files(image_path: Path, size: tuple[int, int], depth_path: Path | None = None,
                      check_depth: bool = False) -> None:
    """At dataset load: the image has the dataset's size; registered depth (if asked) is a
    16-bit single-channel image of the same size. Reads headers only."""
    got = image_size(image_path)
    if got != tuple(size):
        raise InputError(f"{image_path}: image is {got[0]}x{got[1]}, the dataset's images are "
                         f"{size[0]}x{size[1]}")
    if check_depth and depth_path is not None:
        w, h, channels, bits = image_header(depth_path, "depth")
        if channels != 1 or bits != 16:
            raise InputError(f"{depth_path}: depth must be a 16-bit single-channel image, got "
                             f"{channels} channel(s) of {bits} bits")
        if (w, h) != tuple(size):
            raise InputError(f"{depth_path}: depth is {w}x{h}, its image is "
                             f"{size[0]}x{size[1]} (registered depth must match)")


