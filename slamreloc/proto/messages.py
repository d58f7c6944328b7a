"""Messages of `slamreloc.v1` <-> slamreloc's types, with every check on untrusted input.

Everything a request carries is checked here before any work: images through
`slamreloc.io.images` (header bounds before decoding, the extractor's memory bound), cameras
through `Camera` (the same checks as `--intrinsics` / `--camera`), poses through `Rigid3`
(finite, unit quaternion, translation bound), depth by size and encoding. A defect raises
`ServiceError` with its `ErrorKind`; the server turns that into a gRPC status (unary calls) or a
`SessionError` (sessions), and nothing else happens.
"""

from __future__ import annotations

import hmac
import unicodedata

import cv2
import grpc
import numpy as np

from slamreloc.errors import InputError, quoted
from slamreloc.geometry import MAX_COORDINATE, Rigid3, unit_quaternion
from slamreloc.io.images import (
    check_image_size,
    clean_depth_m,
    decode_image,
    decode_rgb,
    depth_from_raw,
    depth_units_problem,
    encoded_header,
)
from slamreloc.proto import relocalizer_pb2 as pb
from slamreloc.types import Camera

ERROR_METADATA_KEY = "slamreloc-error"  # trailing metadata: the ErrorKind's name
DEPTH_REFERENCE_SIZE = (640, 480)  # a request's depth camera is held at this size (pixels)


MAX_MAP_NAME = 128  # characters of a served map's name


def map_name_problem(name: str) -> str | None:
    """Why `name` cannot name a served map (None when it can): 1 to MAX_MAP_NAME printable
    characters without spaces (no control, format or line characters: the name is printed in
    the server's log and sent in every MapInfo)."""
    if not name:
        return "is empty"
    if len(name) > MAX_MAP_NAME:
        return f"has {len(name)} characters, more than {MAX_MAP_NAME}"
    bad = next((c for c in name if not c.isprintable() or c.isspace()), None)
    if bad is not None:
        return f"holds {bad!a}: printable characters without spaces only"
    composed = unicodedata.normalize("NFC", name)
    if composed != name:  # two spellings of one visible name would name two maps
        return (f"is not in Unicode's composed form (NFC), so it looks like another name: "
                f"give it as {quoted(composed)}")
    return None


# the bytes of a saved map's name: NAME_MAX (255) less what the map writer's hidden temporary
# sibling `.NAME.tmp-PID` adds to it ("." and ".tmp-" and a PID of up to 7 digits)
MAX_SAVED_NAME_BYTES = 255 - len("." + ".tmp-") - 7


def saved_map_name_problem(name: str) -> str | None:
    """Why `name` cannot name a map a session saves (None when it can): a map name
    (`map_name_problem`) that is also one plain folder name under the server's
    `--learned-maps` folder: no '/' or '\\', not starting with '.' (nor '.' or '..': the
    writers' temporary folders are hidden siblings), valid Unicode of at most
    MAX_SAVED_NAME_BYTES bytes of UTF-8 (a file system bounds a name in bytes, not in
    characters)."""
    problem = map_name_problem(name)
    if problem:
        return problem
    if "/" in name or "\\" in name:
        return "holds a path separator: a plain name, the server chooses the folder"
    if name.startswith("."):
        return "starts with '.': a plain visible name"
    try:
        size = len(name.encode("utf-8"))
    except UnicodeEncodeError:
        return "is not valid Unicode text (it holds a lone surrogate)"
    if size > MAX_SAVED_NAME_BYTES:
        return (f"is {size} bytes of UTF-8, more than {MAX_SAVED_NAME_BYTES} (a folder's name "
                "is bounded in bytes by the file system)")
    return None


def short_message(text: str, limit: int = 1000) -> str:
    """A refusal's whole message on one line and within `limit` bytes of UTF-8 (gRPC sends it
    percent-encoded in a trailer, at most 3 bytes per byte: well within its 8 KiB bound)."""
    text = " ".join(str(text).split())
    data = text.encode("utf-8", "replace")
    if len(data) <= limit:
        return data.decode("utf-8")  # a lone surrogate, which gRPC could not send, is "?"
    return f"{data[:limit].decode('utf-8', 'ignore')}... ({len(text)} characters)"


class ServiceError(Exception):
    """A request the service refuses: `kind` is a `pb.ErrorKind` value."""

    def __init__(self, kind: int, message: str):
        message = short_message(message)  # whatever it echoes, it fits a status trailer
        super().__init__(message)
        self.kind, self.message = kind, message

    @property
    def kind_name(self) -> str:
        return pb.ErrorKind.Name(self.kind)

    @property
    def grpc_code(self) -> grpc.StatusCode:
        return GRPC_CODES.get(self.kind, grpc.StatusCode.INVALID_ARGUMENT)


# the gRPC status each kind of refusal is answered with (every server of the protocol)
MIN_TOKEN = 16  # characters of an access token
# a client's wait for an answer, seconds (clients/cpp's --timeout too): gRPC's deadline
# arithmetic overflows far beyond the top, and below the bottom every call fails at once
CLIENT_TIMEOUT_S = (0.001, 1e6)
# A learning session's save waits up to this for each of two training rounds (the running one
# and a final one) before its map is written; clients wait that long more than their timeout.
SAVE_WAIT_S = 300.0
# What a client allows a session's close (its final graph optimisation, its trajectory) beyond
# its timeout: a bound, so a server that never answers cannot hold the client forever.
CLOSE_WAIT_S = 300.0


# the blanks dropped around a token where it is read (a file, $SLAMRELOC_TOKEN, a client's
# argument): ASCII's, as clients/cpp drops them; other whitespace (a no-break space, U+2028)
# stays and is refused by `token_problem`
TOKEN_BLANKS = " \t\r\n\v\f"


def token_problem(token: str) -> str | None:
    """Why `token` cannot be a server's or a client's token (None when it can): at least
    MIN_TOKEN characters of printable ASCII without spaces - what gRPC metadata carries, so a
    client can send it at all (clients/cpp applies the same rule)."""
    if len(token) < MIN_TOKEN:
        return f"must have at least {MIN_TOKEN} characters"
    bad = next((c for c in token if not 0x21 <= ord(c) <= 0x7E), None)
    if bad is not None:
        return (f"must be printable ASCII without spaces or line breaks (gRPC metadata carries "
                f"nothing else), got {bad!a}")
    return None


def bearer_matches(values: list, token: str) -> bool:
    """Whether a call's `authorization` metadata `values` carry `token`: exactly one value
    (two are refused whatever their order), `Bearer TOKEN` with the scheme in any case (RFC
    7235), the token compared in constant time. The one check of both engines."""
    if len(values) != 1 or not isinstance(values[0], str):
        return False
    scheme, _, given = values[0].partition(" ")
    return scheme.lower() == "bearer" and hmac.compare_digest(given.encode(), token.encode())


GRPC_CODES = {
    pb.UNKNOWN_MAP: grpc.StatusCode.NOT_FOUND,
    pb.TOO_LARGE: grpc.StatusCode.RESOURCE_EXHAUSTED,
    pb.OVERLOADED: grpc.StatusCode.RESOURCE_EXHAUSTED,
    pb.UNAUTHENTICATED: grpc.StatusCode.UNAUTHENTICATED,
    pb.INTERNAL: grpc.StatusCode.INTERNAL,
    pb.FAILED_PRECONDITION: grpc.StatusCode.FAILED_PRECONDITION,
}  # the others (BAD_*): INVALID_ARGUMENT


# ---- poses ---------------------------------------------------------------------------------
def transform_msg(a_from_b: Rigid3) -> pb.Transform:
    qx, qy, qz, qw = (float(v) for v in a_from_b.quat_xyzw())
    tx, ty, tz = (float(v) for v in a_from_b.translation)
    return pb.Transform(tx=tx, ty=ty, tz=tz, qx=qx, qy=qy, qz=qz, qw=qw)


def rigid_from_msg(msg: pb.Transform, what: str) -> Rigid3:
    """A checked Rigid3: finite values, a unit quaternion (within 1e-3), translation within
    MAX_COORDINATE metres."""
    t = np.array([msg.tx, msg.ty, msg.tz], np.float64)
    q = np.array([msg.qx, msg.qy, msg.qz, msg.qw], np.float64)
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(q))):
        raise ServiceError(pb.BAD_POSE, f"{what}: non-finite values")
    if np.abs(t).max() > MAX_COORDINATE:
        raise ServiceError(pb.BAD_POSE, f"{what}: translation beyond {MAX_COORDINATE:g} m")
    try:
        q = unit_quaternion(q, what)  # the rule of every pose file too
    except InputError as err:
        raise ServiceError(pb.BAD_POSE, str(err)) from None
    return Rigid3.from_qt(q, t)


# ---- images and cameras --------------------------------------------------------------------
def image_from_msg(msg: pb.Image, fits=None, what: str = "image") -> np.ndarray:
    """RGB uint8 (H, W, 3). `fits(width, height, source)`: the extractor's memory bound,
    checked on the header before anything is decoded."""
    kind = msg.WhichOneof("data")
    if kind is None:
        raise ServiceError(pb.BAD_REQUEST, f"{what}: missing")
    try:
        if kind == "encoded":
            return decode_rgb(msg.encoded, what, fits)
        raw = msg.raw
        if raw.channels not in (1, 3):
            raise InputError(f"{what}: raw images have 1 or 3 channels, got {raw.channels}")
        check_image_size(raw.width, raw.height, what)
        if fits is not None:
            fits(raw.width, raw.height, what)
        expected = raw.width * raw.height * raw.channels
        if len(raw.data) != expected:
            raise InputError(f"{what}: {raw.width}x{raw.height}x{raw.channels} needs {expected} "
                             f"bytes, got {len(raw.data)}")
        pixels = np.frombuffer(raw.data, np.uint8).reshape(raw.height, raw.width, raw.channels)
        return np.ascontiguousarray(np.repeat(pixels, 3, axis=2) if raw.channels == 1
                                    else pixels)
    except InputError as err:
        raise ServiceError(_bound_kind(err, pb.BAD_IMAGE), str(err)) from None


def _bound_kind(err: InputError, kind: int) -> int:
    """TOO_LARGE for an input over a bound of `slamreloc.io.limits` (pixels, bytes, memory, JPEG
    scans: "... over the N limit"; Pillow's own pixel bound for BMP, PNM, ...), else `kind`."""
    text = str(err)
    over = ("beyond" in text or "exceeds" in text or "DecompressionBomb" in text
            or ("over the" in text and "limit" in text))
    return pb.TOO_LARGE if over else kind


def camera_from_msg(msg: pb.Camera | None, width: int, height: int, default: Camera,
                    what: str = "camera") -> Camera:
    """The query camera for an image of width x height: the message's (a pinhole camera must
    have the image's size; a COLMAP camera is scaled to it, as `localize --camera`), else
    `default` scaled to the image."""
    kind = None if msg is None else msg.WhichOneof("model")
    try:
        if kind is None:  # (a camera of another aspect ratio is never stretched: for_image)
            return default.for_image(width, height, f"{what}: the map's camera")
        if kind == "pinhole":
            p = msg.pinhole
            if (p.width, p.height) != (width, height):
                raise InputError(f"{p.width}x{p.height}, the image is {width}x{height}")
            return Camera(p.width, p.height, p.fx, p.fy, p.cx, p.cy)
        if msg.colmap.split()[:1] and msg.colmap.split()[0].isdigit():
            raise InputError("a COLMAP camera string without its camera id, 'MODEL WIDTH "
                             f"HEIGHT PARAMS...', got {quoted(msg.colmap[:60])}")
        return Camera.parse(msg.colmap, what).for_image(width, height, what)
    except (InputError, ValueError, OverflowError, ZeroDivisionError) as err:
        text = str(err)  # Camera.parse names its source already
        raise ServiceError(pb.BAD_CAMERA, text if text.startswith(f"{what}:")
                           else f"{what}: {text}") from None


def camera_msg(camera: Camera) -> pb.Camera:
    """A Camera as the message (COLMAP string for a lens model, else pinhole)."""
    if camera.distorted:
        return pb.Camera(colmap=camera.colmap_string())
    return pb.Camera(pinhole=pb.PinholeCamera(width=camera.width, height=camera.height,
                                              fx=camera.fx, fy=camera.fy, cx=camera.cx,
                                              cy=camera.cy))


# ---- depth ---------------------------------------------------------------------------------
def depth_camera_from_msg(msg: pb.PinholeCamera, what: str) -> Camera:
    """The camera that took depth not registered to the image (`Depth.depth_camera`,
    `SessionOpen.depth_camera`; pinhole, pixels), checked and held at DEPTH_REFERENCE_SIZE
    (640x480): every use scales it to its depth map's size (`slamreloc.rgbd.camera_of_depth`),
    a camera that does not hold at that size is refused here, when it is given, and the
    arithmetic, hence the poses, are those of earlier versions of the service. Its aspect
    ratio is checked against each depth map by `check_depth_camera`."""
    try:
        cam = Camera(msg.width, msg.height, msg.fx, msg.fy, msg.cx, msg.cy)
    except (InputError, ValueError, ZeroDivisionError) as err:
        raise ServiceError(pb.BAD_CAMERA, f"{what}: {err}") from None
    try:
        return cam.scaled_to(*DEPTH_REFERENCE_SIZE)
    except (InputError, ValueError, ZeroDivisionError) as err:
        w, h = DEPTH_REFERENCE_SIZE
        raise ServiceError(pb.BAD_CAMERA, f"{what}: {msg.width}x{msg.height} fx={msg.fx:g} "
                           f"fy={msg.fy:g} is held scaled to {w}x{h}, and there {err}") from None


def check_depth_camera(msg: pb.PinholeCamera, depth: np.ndarray, what: str) -> None:
    """BAD_CAMERA naming `what` unless the depth camera as given (`msg`, checked by
    `depth_camera_from_msg`) has the depth map's aspect ratio: `Camera.for_image`, the one
    rule wherever a camera meets an image (never stretched)."""
    try:
        Camera(msg.width, msg.height, msg.fx, msg.fy, msg.cx, msg.cy).for_image(
            depth.shape[1], depth.shape[0], f"{what} for the depth map")
    except InputError as err:
        raise ServiceError(pb.BAD_CAMERA, str(err)) from None


DEPTH_ITEM_BYTES = {pb.Depth.UINT16: 2, pb.Depth.FLOAT32_METRES: 4}  # raw encodings


def depth_from_msg(msg: pb.Depth, registered_size: tuple[int, int] | None,
                   units_per_metre: float = 0.0, what: str = "depth") -> np.ndarray:
    """float32 metres (H, W), 0 where there is no depth. `registered_size`: the image's (width,
    height), which depth registered to it must have; None for depth of its own camera."""
    units = msg.units_per_metre or units_per_metre or 1000.0
    try:
        if msg.encoding == pb.Depth.FLOAT32_METRES and msg.units_per_metre != 0:
            raise InputError(f"units_per_metre {msg.units_per_metre:.10g} given with "
                             "FLOAT32_METRES depth, which is in metres: units apply to UINT16 "
                             "and PNG16 depth only (leave it 0)")
        problem = (None if msg.encoding == pb.Depth.FLOAT32_METRES
                   else depth_units_problem(units))
        if problem:
            raise InputError(f"units_per_metre {problem}")
        if msg.encoding != pb.Depth.PNG16 and msg.encoding not in DEPTH_ITEM_BYTES:
            raise InputError(f"unknown encoding {msg.encoding} (PNG16, UINT16 or "
                             "FLOAT32_METRES)")
        if msg.encoding == pb.Depth.PNG16:
            header = encoded_header(msg.data, what, "depth")  # colour would become grey
            if header.channels != 1 or header.bits != 16:
                raise InputError(f"a 16-bit single-channel PNG is needed, got {header.channels} "
                                 f"channel(s) of {header.bits} bits")
            if (msg.width or msg.height) and (msg.width, msg.height) != (header.width,
                                                                         header.height):
                raise InputError(f"the PNG is {header.width}x{header.height}, width and height "
                                 f"say {msg.width}x{msg.height} (give the PNG's, or leave "
                                 "both 0)")
            raw = decode_image(msg.data, what, cv2.IMREAD_ANYDEPTH, "depth")
            if raw.ndim != 2 or raw.dtype != np.uint16:
                raise InputError(f"a 16-bit single-channel PNG is needed, got {raw.dtype} "
                                 f"{raw.shape}")
            depth = depth_from_raw(raw, units)
        else:
            check_image_size(msg.width, msg.height, what, "depth")
            item = DEPTH_ITEM_BYTES[msg.encoding]
            expected = msg.width * msg.height * item
            if len(msg.data) != expected:
                raise InputError(f"{msg.width}x{msg.height} needs {expected} bytes, got "
                                 f"{len(msg.data)}")
            if msg.encoding == pb.Depth.FLOAT32_METRES:
                depth = clean_depth_m(np.frombuffer(msg.data, "<f4")
                                      .reshape(msg.height, msg.width).copy())
            else:
                depth = depth_from_raw(np.frombuffer(msg.data, "<u2")
                                       .reshape(msg.height, msg.width), units)
        if registered_size is not None and (depth.shape[1], depth.shape[0]) != registered_size:
            w, h = registered_size
            raise InputError(f"registered depth is {depth.shape[1]}x{depth.shape[0]}, the image "
                             f"is {w}x{h} (give the depth camera if it is not registered)")
        return depth
    except InputError as err:  # the image checks name the field themselves
        text = str(err) if str(err).startswith(f"{what}: ") else f"{what}: {err}"
        raise ServiceError(_bound_kind(err, pb.BAD_DEPTH), text) from None
