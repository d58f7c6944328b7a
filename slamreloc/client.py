"""Python client of `slamreloc serve` (protocol slamreloc.v1; docs/serve.md).

    from slamreloc.client import Client

    with Client("127.0.0.1:50051") as client:
        result = client.localize("query.jpg", map="kitchen")
        if result.localized:
            print(result.world_from_cam.translation, result.response.num_inliers)

        with client.session(map="kitchen") as session:  # a SLAM system's session
            for image, odom_from_cam in frames:
                update = session.send(image, odometry_world_from_cam=odom_from_cam)
                for event in update.events: ...

Images go as file bytes (a path or `bytes`) or raw RGB / grey uint8 arrays; cameras as a
`slamreloc.types.Camera` or a COLMAP camera string; poses as `Rigid3` (`world_from_cam`: camera
to map frame, metres). A refusal raises `RemoteError` with the server's ErrorKind name.
"""

from __future__ import annotations

import queue
import threading
from dataclasses import dataclass
from pathlib import Path

import grpc
import numpy as np

from slamreloc.errors import InputError, quoted
from slamreloc.geometry import Rigid3
from slamreloc.io.address import target_problem
from slamreloc.io.pem import check_pem, read_pem, trusted_certificates_problem
from slamreloc.proto import relocalizer_pb2 as pb
from slamreloc.proto.messages import (
    CLIENT_TIMEOUT_S,
    CLOSE_WAIT_S,
    ERROR_METADATA_KEY,
    GRPC_CODES,
    SAVE_WAIT_S,
    TOKEN_BLANKS,
    camera_msg,
    rigid_from_msg,
    map_name_problem,
    saved_map_name_problem,
    token_problem,
    transform_msg,
)
from slamreloc.proto.relocalizer_pb2_grpc import RelocalizerStub
from slamreloc.types import Camera


class RemoteError(Exception):
    """The server refused a call: `kind` is the ErrorKind's name ("BAD_IMAGE", "UNKNOWN_MAP",
    ...; "" when gRPC itself refused, e.g. a message over the size limit), `code` the gRPC
    status."""

    def __init__(self, code: grpc.StatusCode, kind: str, message: str):
        super().__init__(f"{kind or code.name}: {message}")
        self.code, self.kind, self.message = code, kind, message

    @staticmethod
    def from_rpc(err: grpc.RpcError) -> RemoteError:
        kind = dict(err.trailing_metadata() or ()).get(ERROR_METADATA_KEY, "")
        return RemoteError(err.code(), kind, err.details() or "")


@dataclass(frozen=True)
class LocalizeResult:
    response: pb.LocalizeResponse

    @property
    def localized(self) -> bool:
        return self.response.localized

    @property
    def world_from_cam(self) -> Rigid3 | None:
        """The pose found (also when it was refused as far from the prior), else None."""
        if not self.response.HasField("world_from_cam"):
            return None
        return rigid_from_msg(self.response.world_from_cam, "world_from_cam")

    @property
    def reason(self) -> str:
        return pb.NotLocalized.Name(self.response.reason)


def image_msg(image) -> pb.Image:
    """A path or bytes (an encoded image file), or a uint8 array (H, W) / (H, W, 3) RGB."""
    if isinstance(image, (str, Path)):
        from slamreloc.io.fileio import read_bytes

        return pb.Image(encoded=read_bytes(image, "image", "max_image_bytes"))
    if isinstance(image, (bytes, bytearray, memoryview)):
        return pb.Image(encoded=bytes(image))
    arr = np.ascontiguousarray(image)
    if arr.dtype != np.uint8 or arr.ndim not in (2, 3) or (arr.ndim == 3 and arr.shape[2] != 3):
        raise ValueError(f"raw images are uint8 (H, W) or (H, W, 3), got {arr.dtype} "
                         f"{arr.shape}")
    channels = 1 if arr.ndim == 2 else 3
    return pb.Image(raw=pb.RawImage(width=arr.shape[1], height=arr.shape[0], channels=channels,
                                    data=arr.tobytes()))


def _depth_image(depth: np.ndarray) -> np.ndarray:
    """`depth`, checked to be one value per pixel: (H, W)."""
    if depth.ndim != 2:
        raise InputError(f"depth is (H, W), one value per pixel; got shape {depth.shape}")
    return depth


def depth_msg(depth: np.ndarray, camera: Camera | None = None) -> pb.Depth:
    """float32 metres (H, W), 0 where unknown; `camera`: the camera that took the depth when it
    is not registered to the image (`Frame.depth_camera`; sent as its pinhole camera, any
    size: the server scales it to the depth map)."""
    if np.asarray(depth).dtype.kind != "f":  # raw sensor units sent as metres: 1732 m
        raise InputError(f"depth is {np.asarray(depth).dtype}: metres are floats (float32 "
                         "metres, or raw uint16 with depth_encoding=\"uint16\" in a session)")
    d = _depth_image(np.ascontiguousarray(depth, "<f4"))
    msg = pb.Depth(encoding=pb.Depth.FLOAT32_METRES, width=d.shape[1], height=d.shape[0],
                   data=d.tobytes())
    if camera is not None:
        msg.depth_camera.CopyFrom(camera_msg(camera.pinhole).pinhole)
    return msg


def _pose_msg(pose: Rigid3, what: str) -> pb.Transform:
    """The wire's Transform of a pose the caller gives; InputError naming `what` for one that
    is no rigid motion (a reflection, a scaled or sheared rotation block, a translation beyond
    MAX_COORDINATE): the server's and every pose file's rule (`Rigid3.from_matrix`), checked
    before the send instead of a quaternion made up from such a matrix."""
    if not isinstance(pose, Rigid3):
        raise InputError(f"{what} is {type(pose).__name__}, not a Rigid3")
    return transform_msg(Rigid3.from_matrix(pose.matrix(), source=what))


def _camera(camera: Camera | str | None) -> pb.Camera | None:
    if camera is None:
        return None
    return pb.Camera(colmap=camera) if isinstance(camera, str) else camera_msg(camera)


MAX_MESSAGE_BYTES = (2 << 30) - 1  # gRPC's message size is an int32


def _check_map_name(map: str, what: str = "map", rule=map_name_problem) -> str:
    """`map` unless it breaks the server's rule for map names (`map_name_problem`; "" is the
    server's one map): InputError naming `what`, before anything is sent."""
    if not isinstance(map, str):
        raise InputError(f"`{what}` is {type(map).__name__}, not text")
    problem = rule(map) if map else None
    if problem:
        raise InputError(f"`{what}` {quoted(map)} {problem}")
    return map


def _check_arguments(address, token, tls_ca, timeout_s, max_message_bytes) -> None:
    """InputError naming the first argument of `Client` that it could not use (the rules of
    the server and of clients/cpp: `target_problem`, `token_problem`, CLIENT_TIMEOUT_S)."""
    problem = target_problem(address)
    if problem:
        raise InputError(f"`address` {quoted(str(address))} {problem}")
    if token is not None and not isinstance(token, str):
        raise InputError(f"`token` is {type(token).__name__}, not text")
    if tls_ca is not None and not isinstance(tls_ca, (str, Path, bytes, bytearray,
                                                      memoryview)):
        raise InputError(f"`tls_ca` is {type(tls_ca).__name__}: a PEM file's path or bytes")
    low, high = CLIENT_TIMEOUT_S
    if (isinstance(timeout_s, bool) or not isinstance(timeout_s, (int, float))
            or not low <= timeout_s <= high):
        raise InputError(f"`timeout_s` {timeout_s!r}: seconds, {low:g} to {high:g}")
    if (isinstance(max_message_bytes, bool) or not isinstance(max_message_bytes, int)
            or not 1024 <= max_message_bytes <= MAX_MESSAGE_BYTES):
        raise InputError(f"`max_message_bytes` {max_message_bytes!r}: a whole number of bytes, "
                         f"1024 to {MAX_MESSAGE_BYTES}")


class Client:
    """A connection to a server at `address` (HOST:PORT, `target_problem`'s rule). `token`:
    sent as `authorization: Bearer TOKEN` (blanks around it dropped; the server's rule,
    `token_problem`, holds for it); `tls_ca`: the PEM certificate(s) to trust for a TLS server
    (a path or the bytes; InputError when they are no PEM certificate); `timeout_s`: the
    longest wait for a unary call's answer and for a session frame's, CLIENT_TIMEOUT_S (a
    save and a close wait as long as the server takes: it bounds them itself)."""

    def __init__(self, address: str = "127.0.0.1:50051", token: str | None = None,
                 tls_ca: Path | bytes | None = None, timeout_s: float = 60.0,
                 max_message_bytes: int = 64 << 20):
        _check_arguments(address, token, tls_ca, timeout_s, max_message_bytes)
        options = [("grpc.max_send_message_length", max_message_bytes),
                   ("grpc.max_receive_message_length", max_message_bytes)]
        if token is not None:  # the blanks around it dropped, as the server reads its own
            token = token.strip(TOKEN_BLANKS)
            problem = token_problem(token) if token else "is empty (give one, or None for none)"
            if problem:
                raise InputError(f"the token {problem}")
        if tls_ca is not None:
            given = isinstance(tls_ca, (bytes, bytearray, memoryview))  # else a path
            ca = (check_pem(bytes(tls_ca), "certificate", "tls_ca") if given
                  else read_pem(tls_ca, "certificate", "tls_ca"))
            problem = trusted_certificates_problem(ca)
            if problem:
                where = "" if given else f"{tls_ca}: "
                raise InputError(f"{where}`tls_ca` cannot be trusted: {problem}")
            self.channel = grpc.secure_channel(address, grpc.ssl_channel_credentials(ca),
                                               options)
        else:
            self.channel = grpc.insecure_channel(address, options)
        self.stub = RelocalizerStub(self.channel)
        self.metadata = (("authorization", f"Bearer {token}"),) if token else ()
        self.timeout_s = timeout_s

    def _call(self, method, request):
        try:
            return method(request, timeout=self.timeout_s, metadata=self.metadata)
        except grpc.RpcError as err:
            raise RemoteError.from_rpc(err) from None

    def localize(self, image, camera: Camera | str | None = None, map: str = "",
                 depth: np.ndarray | None = None, depth_camera: Camera | None = None,
                 world_from_cam_prior: Rigid3 | None = None) -> LocalizeResult:
        """One image against the map named `map` ("" on a server with one map). camera: the
        map's, scaled to the image, when None. depth: float32 metres (H, W), refines the pose
        on the map's surface; in the pixels of `depth_camera` (the camera that took it, where
        it is not registered to the image), else of the image (registered)."""
        req = pb.LocalizeRequest(map=_check_map_name(map), image=image_msg(image))
        if camera is not None:
            req.camera.CopyFrom(_camera(camera))
        if depth is not None:
            req.depth.CopyFrom(depth_msg(depth, depth_camera))
        if world_from_cam_prior is not None:
            req.world_from_cam_prior.CopyFrom(_pose_msg(world_from_cam_prior,
                                                        "`world_from_cam_prior`"))
        return LocalizeResult(self._call(self.stub.Localize, req))

    def health(self) -> pb.HealthResponse:
        return self._call(self.stub.Health, pb.HealthRequest())

    def list_maps(self) -> list[pb.MapInfo]:
        return list(self._call(self.stub.ListMaps, pb.ListMapsRequest()).maps)

    def reload_map(self, map: str = "") -> pb.ReloadMapResponse:
        return self._call(self.stub.ReloadMap, pb.ReloadMapRequest(map=_check_map_name(map)))

    def session(self, map: str = "", odometry: str = "client",
                depth_camera: Camera | None = None,
                depth_units_per_metre: float = 0.0, learn: bool = False) -> ClientSession:
        """Open a session; see `ClientSession`. depth_camera: the camera that took the frames'
        depth where it is not registered to the images (`Frame.depth_camera`), else None.
        learn: no map; the session learns one from the frames' depth (`ClientSession.save`
        writes it on the server)."""
        opening = pb.SessionOpen(map=_check_map_name(map), odometry=odometry, learn=learn,
                                 depth_units_per_metre=depth_units_per_metre)
        if depth_camera is not None:
            opening.depth_camera.CopyFrom(camera_msg(depth_camera.pinhole).pinhole)
        return ClientSession(self, opening)

    def close(self) -> None:
        self.channel.close()

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def frame_poses(results: list[pb.FrameResult]) -> list[Rigid3 | None]:
    """Each session frame's map-frame pose (world_from_cam) as the server returned it, None
    where it had none (before the first anchor)."""
    return [rigid_from_msg(r.world_from_cam, f"frame {r.index}") if r.has_pose else None
            for r in results]


DEPTH_ENCODINGS = ("float32", "uint16")  # `ClientSession.send`'s depth: metres, or depth units

CONFIRMING = (pb.SessionEvent.TRACKING_RECOVERED, pb.SessionEvent.LOOP_CLOSURE)


def confirmed_frames(results: list[pb.FrameResult]) -> list[int]:
    """The frames where a relocalization confirmed a map-frame pose (recovery after loss, or
    a loop closure), in order: with `frame_poses`, what `slamreloc.slam.report.kidnap_stats`
    scores."""
    return [e.frame for r in results for e in r.events if e.kind in CONFIRMING]


def _unexpected(update: pb.SessionUpdate, wanted: str) -> RemoteError:
    got = update.WhichOneof("message") or "an empty answer"
    return RemoteError(grpc.StatusCode.UNKNOWN, "", f"the server answered {got} where "
                       f"{wanted} was due")


def _expected(update: pb.SessionUpdate, wanted: str) -> pb.SessionUpdate:
    """`update` if it is the answer `wanted`; RemoteError for a refusal (its kind's status
    code) or any other answer."""
    kind = update.WhichOneof("message")
    if kind == "error":
        raise RemoteError(GRPC_CODES.get(update.error.kind, grpc.StatusCode.INVALID_ARGUMENT),
                          pb.ErrorKind.Name(update.error.kind), update.error.message)
    if kind != wanted:
        raise _unexpected(update, wanted)
    return update


class ClientSession:
    """A session in lock-step: `send` one frame, get its `pb.FrameResult`; `close` ends it and
    returns the final trajectory (`pb.SessionClosed`). A refused frame raises RemoteError and
    the session carries on."""

    _END = object()

    def __init__(self, client: Client, opening: pb.SessionOpen):
        self._requests: queue.Queue = queue.Queue()
        self._requests.put(pb.SessionRequest(open=opening))
        self._updates = client.stub.Session(iter(self._requests.get, self._END),
                                            metadata=client.metadata)
        # the stream's answers, read by a thread of their own so that each wait is bounded by
        # the client's `timeout_s`, as a unary call is
        self._timeout_s = client.timeout_s
        self._answers: queue.Queue = queue.Queue()
        try:
            threading.Thread(target=self._read, name="slamreloc-session", daemon=True).start()
            first = self._next()
            if first.WhichOneof("message") != "opened":
                raise _unexpected(first, "opened")
        except BaseException:  # whatever fails once the stream is open frees its server slot
            self._updates.cancel()
            raise
        self.opened: pb.SessionOpened = first.opened
        self.closed: pb.SessionClosed | None = None

    def _read(self) -> None:
        try:
            for update in self._updates:
                self._answers.put(update)
            self._answers.put(None)  # the server ended the stream
        except grpc.RpcError as err:
            self._answers.put(err)

    def _next(self, more_s: float = 0.0, what: str = "") -> pb.SessionUpdate:
        """The next answer; RemoteError where the stream failed, ended without one, or none
        came within the client's `timeout_s` and `more_s` seconds more (the server's own bound
        on `what` it does first: a save's training rounds, a close's final optimisation); the
        stream is then cancelled."""
        wait_s = self._timeout_s + more_s
        try:
            update = self._answers.get(timeout=wait_s)
        except queue.Empty:
            self._updates.cancel()
            allowed = ("the client's timeout_s" if not more_s else
                       f"the client's timeout_s {self._timeout_s:g} s and {more_s:g} s for "
                       f"{what}")
            raise RemoteError(grpc.StatusCode.DEADLINE_EXCEEDED, "", f"no answer within "
                              f"{wait_s:g} s ({allowed}); the session is cancelled") from None
        if update is None:
            self._answers.put(None)  # every later read ends the same way
            raise RemoteError(grpc.StatusCode.UNAVAILABLE, "", "the server ended the session "
                              "without an answer")
        if isinstance(update, grpc.RpcError):
            self._answers.put(update)
            raise RemoteError.from_rpc(update)
        return update

    def send(self, image, camera: Camera | str | None = None, depth: np.ndarray | None = None,
             odometry_world_from_cam: Rigid3 | None = None, timestamp: float = 0.0,
             depth_encoding: str = "float32") -> pb.FrameResult:
        """One frame. depth: float32 metres (H, W); with depth_encoding="uint16" a uint16
        array in the session's depth units. odometry_world_from_cam: required with client
        odometry (the client's pose in its own fixed odometry frame)."""
        if depth_encoding not in DEPTH_ENCODINGS:
            raise InputError(f"`depth_encoding` {depth_encoding!r}: one of "
                             f"{', '.join(DEPTH_ENCODINGS)}")
        frame = pb.SessionFrame(image=image_msg(image), timestamp=timestamp)
        if camera is not None:
            frame.camera.CopyFrom(_camera(camera))
        if depth is not None:
            if depth_encoding == "uint16":
                raw = _depth_image(np.asarray(depth))
                if raw.dtype.kind not in "ui" or (raw.size and (raw.min() < 0
                                                                or raw.max() > 65535)):
                    raise InputError(f"depth is {raw.dtype}: depth_encoding=\"uint16\" "
                                     "sends raw whole units 0..65535 (metres: float32)")
                d = np.ascontiguousarray(raw, "<u2")
                frame.depth.CopyFrom(pb.Depth(encoding=pb.Depth.UINT16, width=d.shape[1],
                                              height=d.shape[0], data=d.tobytes()))
            else:
                frame.depth.CopyFrom(depth_msg(depth))
        if odometry_world_from_cam is not None:
            frame.odometry_world_from_cam.CopyFrom(_pose_msg(odometry_world_from_cam,
                                                            "`odometry_world_from_cam`"))
        return self._answer(pb.SessionRequest(frame=frame)).frame

    def save(self, name: str) -> pb.MapSaved:
        """A learning session's map, saved on the server (in its `--learned-maps` folder) and
        served as the map `name` from then on; saving again replaces it. The session carries
        on. RemoteError where the server refuses (FAILED_PRECONDITION: no `--learned-maps`, no
        training round yet, a name taken; BAD_REQUEST: not a plain map name)."""
        if not name:
            raise InputError("`name` is empty: the name to save the map under")
        _check_map_name(name, "name", saved_map_name_problem)
        return self._answer(pb.SessionRequest(save=pb.SessionSave(name=name))).saved

    def _answer(self, request: pb.SessionRequest) -> pb.SessionUpdate:
        """Send one request and read its answer, which must be the one it asks for (a frame's
        `frame`, a save's `saved`); a `SessionError` raises RemoteError with the status code of
        its kind, as unary calls' refusals do, and any other answer RemoteError UNKNOWN."""
        if self.closed is not None:
            raise RemoteError(grpc.StatusCode.FAILED_PRECONDITION, "",
                              "the session is closed: open a new one")
        self._requests.put(request)
        if request.HasField("save"):  # the server waits for up to two training rounds
            return _expected(self._next(2 * SAVE_WAIT_S, "the save's training rounds"),
                             "saved")
        return _expected(self._next(), "frame")

    def close(self) -> pb.SessionClosed:
        """End the session: its final trajectory (`pb.SessionClosed`); RemoteError where the
        server refuses or ends the stream without it, or sends nothing within the client's
        `timeout_s` and `CLOSE_WAIT_S` more for its final optimisation."""
        if self.closed is None:
            self._requests.put(self._END)
            self.closed = _expected(self._next(CLOSE_WAIT_S, "the final optimisation"),
                                    "closed").closed
        return self.closed

    def __enter__(self) -> ClientSession:
        return self

    def __exit__(self, *exc) -> None:
        if exc[0] is None:
            self.close()
        else:
            self._updates.cancel()
