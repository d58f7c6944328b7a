"""The gRPC server of `slamreloc serve`: maps loaded once, requests on a thread pool.

Concurrency: `workers` localizations run at once (a semaphore shared by `Localize` and session
frames); with more than one, torch's threads are split between them. Each session holds one
thread of the pool for its lifetime, and at most `max_sessions` are open.

Safety: the server binds 127.0.0.1 unless told otherwise, and a non-local address needs a token
(`authorization: Bearer TOKEN` metadata, compared in constant time) or TLS with a token. Messages
are parsed here, not by gRPC, so a body that is not the method's message is a typed
`BAD_REQUEST`; one over `max_request_bytes` is refused by gRPC (RESOURCE_EXHAUSTED) before it is
read. Every refusal is a status code plus the ErrorKind's name in the `slamreloc-error`
trailing metadata; an unexpected exception is logged and answered INTERNAL, and the server
carries on. Nothing on the wire is pickled: protobuf only.
"""

from __future__ import annotations

import hmac
import ipaddress
import os
import signal
import sys
import threading
import time
import traceback
from concurrent import futures
from dataclasses import dataclass
from pathlib import Path

import grpc
from google.protobuf.message import DecodeError

from slamreloc import __version__
from slamreloc.errors import InputError, OutOfMemory, is_out_of_memory
from slamreloc.proto import PROTOCOL
from slamreloc.proto import relocalizer_pb2 as pb
from slamreloc.proto.messages import ERROR_METADATA_KEY, ServiceError, quoted
from slamreloc.service.localize import localize
from slamreloc.service.maps import MapRegistry
from slamreloc.service.sessions import Session

SERVICE_NAME = pb.DESCRIPTOR.services_by_name["Relocalizer"].full_name
LOOPBACK_NAMES = ("localhost",)


@dataclass(frozen=True)
class ServeConfig:
    host: str = "127.0.0.1"
    port: int = 50051  # 0: any free port (RunningServer.port says which)
    workers: int = 1  # localizations at once
    max_sessions: int = 8
    token: str | None = None  # required by every call when set
    tls_cert: Path | None = None  # PEM files; both or neither
    tls_key: Path | None = None
    max_request_bytes: int = 32 << 20
    watch_s: float = 2.0  # reload maps whose folder was replaced; 0: only on ReloadMap
    load_timeout_s: float = 300.0  # a reload reading a map folder longer is refused (OVERLOADED)

    def check(self) -> None:
        """InputError for a configuration that must not run (a non-local bind without a token,
        half a TLS pair, out-of-range numbers)."""
        if not 0 <= self.port <= 65535:
            raise InputError(f"`port` {self.port}: not a TCP port")
        if not 1 <= self.workers <= 256:
            raise InputError(f"`workers` {self.workers}: 1 to 256")
        if not 1 <= self.max_sessions <= 4096:
            raise InputError(f"`max_sessions` {self.max_sessions}: 1 to 4096")
        if not (1 << 16) <= self.max_request_bytes <= (2 << 30) - 1:
            raise InputError(f"`max_request_bytes` {self.max_request_bytes}: 65536 to "
                             f"{(2 << 30) - 1}")
        if not 0 <= self.watch_s < float("inf"):  # NaN too
            raise InputError(f"`watch_s` {self.watch_s}: seconds between checks, 0 (only "
                             "ReloadMap) or more")
        if not 0 < self.load_timeout_s < float("inf"):
            raise InputError(f"`load_timeout_s` {self.load_timeout_s}: seconds, more than 0")
        if (self.tls_cert is None) != (self.tls_key is None):
            raise InputError("`tls_cert` and `tls_key` go together")
        if self.token is not None and len(self.token) < 16:
            raise InputError("the token must have at least 16 characters")
        if not is_loopback(self.host) and self.token is None:
            raise InputError(f"`host` {self.host} is not a loopback address: anyone who reaches "
                             "it could use the server; give a token (`token_file` or "
                             "SLAMRELOC_TOKEN), and TLS (`tls_cert`/`tls_key`) off a trusted "
                             "network")


def is_loopback(host: str) -> bool:
    if host in LOOPBACK_NAMES:
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def _log(message: str) -> None:
    print(f"slamreloc serve: {message}", file=sys.stderr, flush=True)


class RelocalizerService:
    """The methods of slamreloc.v1.Relocalizer over a MapRegistry."""

    def __init__(self, registry: MapRegistry, config: ServeConfig):
        self.registry, self.config = registry, config
        self.compute = threading.BoundedSemaphore(config.workers)
        self.started = time.time()
        self._count_lock = threading.Lock()
        self.sessions = 0
        self.requests = 0

    # ---- plumbing ------------------------------------------------------------------------
    def _refuse(self, context: grpc.ServicerContext, err: ServiceError):
        context.set_trailing_metadata(((ERROR_METADATA_KEY, err.kind_name),))
        context.abort(err.grpc_code, err.message)

    def _authorized(self, context: grpc.ServicerContext) -> bool:
        if self.config.token is None:
            return True
        given = dict(context.invocation_metadata()).get("authorization", "")
        return hmac.compare_digest(given.encode(), f"Bearer {self.config.token}".encode())

    def _unary(self, parse, handle):
        """A unary method: count, authenticate, parse the bytes, answer or refuse."""

        def method(body: bytes, context: grpc.ServicerContext):
            with self._count_lock:
                self.requests += 1
            try:
                if not self._authorized(context):
                    raise ServiceError(pb.UNAUTHENTICATED, "missing or wrong token")
                return handle(parse_message(parse, body))
            except ServiceError as err:
                self._refuse(context, err)
            except Exception as err:  # noqa: BLE001 - answer, log, and keep serving
                self._refuse(context, unexpected(err))

        return method

    # ---- methods ---------------------------------------------------------------------------
    def localize(self, request: pb.LocalizeRequest) -> pb.LocalizeResponse:
        served = self.registry.get(request.map)
        with self.compute:
            return localize(served, request)

    def health(self, _: pb.HealthRequest) -> pb.HealthResponse:
        return pb.HealthResponse(serving=True, protocol=PROTOCOL, version=__version__,
                                 num_maps=len(self.registry.names), num_sessions=self.sessions,
                                 uptime_s=time.time() - self.started,
                                 num_requests=self.requests)

    def list_maps(self, _: pb.ListMapsRequest) -> pb.ListMapsResponse:
        return pb.ListMapsResponse(maps=[m.info() for m in self.registry.all()])

    def reload_map(self, request: pb.ReloadMapRequest) -> pb.ReloadMapResponse:
        served, changed = self.registry.reload(request.map)
        if changed:
            _log(f"map {quoted(served.name)} reloaded: version {served.version}")
        return pb.ReloadMapResponse(map=served.info(), changed=changed)

    def session(self, requests, context: grpc.ServicerContext):
        """Session stream: SessionOpen first, then frames; ends with SessionClosed."""
        with self._count_lock:
            self.requests += 1
        if not self._authorized(context):
            self._refuse(context, ServiceError(pb.UNAUTHENTICATED, "missing or wrong token"))
        with self._count_lock:
            if self.sessions >= self.config.max_sessions:
                self._refuse(context, ServiceError(
                    pb.OVERLOADED, f"{self.sessions} sessions open, the most this server takes"))
            self.sessions += 1
        try:
            yield from self._session(requests, context)
        finally:
            with self._count_lock:
                self.sessions -= 1

    def _session(self, requests, context):
        session = None
        for body in requests:
            try:
                msg = parse_message(pb.SessionRequest, body)
                kind = msg.WhichOneof("message")
                if session is None:
                    if kind != "open":
                        raise ServiceError(pb.BAD_REQUEST, "a session starts with SessionOpen")
                    session = Session(self.registry.get(msg.open.map), msg.open)
                    yield pb.SessionUpdate(opened=session.opened()).SerializeToString()
                    continue
                if kind != "frame":
                    raise ServiceError(pb.BAD_REQUEST, "SessionOpen twice in one session")
                with self.compute:
                    result = session.frame(msg.frame)
                yield pb.SessionUpdate(frame=result).SerializeToString()
            except ServiceError as err:
                if session is None:  # nothing to carry on with
                    self._refuse(context, err)
                yield pb.SessionUpdate(error=pb.SessionError(
                    kind=err.kind, message=err.message,
                    frame=session.n_frames)).SerializeToString()
            except Exception as err:  # noqa: BLE001
                refusal = unexpected(err)
                if session is None:
                    self._refuse(context, refusal)
                yield pb.SessionUpdate(error=pb.SessionError(
                    kind=refusal.kind, message=refusal.message,
                    frame=session.n_frames)).SerializeToString()
        if session is not None and context.is_active():
            with self.compute:
                closed = session.close()
            yield pb.SessionUpdate(closed=closed).SerializeToString()

    def handler(self) -> grpc.GenericRpcHandler:
        def unary(parse, handle):
            return grpc.unary_unary_rpc_method_handler(
                self._unary(parse, handle), response_serializer=lambda m: m.SerializeToString())

        return grpc.method_handlers_generic_handler(SERVICE_NAME, {
            "Localize": unary(pb.LocalizeRequest, self.localize),
            "Health": unary(pb.HealthRequest, self.health),
            "ListMaps": unary(pb.ListMapsRequest, self.list_maps),
            "ReloadMap": unary(pb.ReloadMapRequest, self.reload_map),
            "Session": grpc.stream_stream_rpc_method_handler(self.session),
        })


def unexpected(err: Exception) -> ServiceError:
    """The refusal for an exception no check raised: TOO_LARGE for an allocation that failed
    (an input whose work did not fit in memory), else INTERNAL, logged with its traceback."""
    if isinstance(err, OutOfMemory) or is_out_of_memory(err):
        _log(f"out of memory: {type(err).__name__}: {' '.join(str(err).split())[:300]}")
        return ServiceError(pb.TOO_LARGE, f"out of memory: {err}" if not
                            isinstance(err, OutOfMemory) else str(err))
    _log(f"internal error: {type(err).__name__}: {err}\n{traceback.format_exc()}")
    return ServiceError(pb.INTERNAL, f"{type(err).__name__}: {err}")


def read_tls_pair(cert: Path, key: Path) -> tuple[bytes, bytes]:
    """(key, certificate chain) PEM bytes, each checked to parse as what it should be;
    InputError naming the file (and its setting) that is not."""
    from slamreloc.io.fileio import read_bytes

    out = []
    for path, option, what in ((key, "tls_key", "private key"),
                               (cert, "tls_cert", "certificate")):
        data = read_bytes(path, f"TLS {what} (`{option}`)", 1 << 20)
        problem = pem_problem(data, what)
        if problem:
            raise InputError(f"{path}: `{option}` is not a PEM {what} ({problem})")
        out.append(data)
    problem = pair_problem(out[0], out[1])
    if problem:
        raise InputError(f"{key}: `tls_key` does not belong to the certificate in {cert} "
                         f"(`tls_cert`): {problem}")
    return out[0], out[1]


def pair_problem(key: bytes, cert: bytes) -> str | None:
    """Why the PEM private key is not the key of the (first) PEM certificate, or None
    (also None without the `cryptography` package to tell)."""
    try:
        from cryptography import x509
        from cryptography.hazmat.primitives import serialization
    except ImportError:
        return None
    try:
        public = serialization.load_pem_private_key(key, password=None).public_key()
        leaf = x509.load_pem_x509_certificates(cert)[0].public_key()
        fmt = (serialization.Encoding.PEM, serialization.PublicFormat.SubjectPublicKeyInfo)
        if public.public_bytes(*fmt) != leaf.public_bytes(*fmt):
            return "their public keys differ"
    except Exception:  # noqa: BLE001 - parsed above; an exotic key type: let gRPC say
        return None
    return None


def pem_problem(data: bytes, what: str) -> str | None:
    """Why `data` is not a PEM `what` ("private key" or "certificate"), or None."""
    marker = b"PRIVATE KEY-----" if what == "private key" else b"-----BEGIN CERTIFICATE-----"
    if marker not in data:
        return "no " + ("'PRIVATE KEY'" if what == "private key" else "'BEGIN CERTIFICATE'") \
            + " block"
    try:
        from cryptography import x509
        from cryptography.hazmat.primitives.serialization import load_pem_private_key
    except ImportError:
        return None
    try:
        if what == "private key":
            load_pem_private_key(data, password=None)
        else:
            x509.load_pem_x509_certificates(data)
    except (ValueError, TypeError) as err:  # cryptography's parse errors
        return " ".join(str(err).split())[:200] or type(err).__name__
    except Exception as err:  # noqa: BLE001 - an unsupported algorithm, a Rust-side error
        return f"{type(err).__name__}: {' '.join(str(err).split())[:200]}"
    return None


def parse_message(cls, body: bytes):
    """The method's message from its bytes; BAD_REQUEST if they are not one."""
    msg = cls()
    try:
        msg.ParseFromString(body)
    except (DecodeError, RuntimeError, ValueError) as err:
        raise ServiceError(pb.BAD_REQUEST, f"not a {cls.DESCRIPTOR.name} message: {err}") \
            from None
    return msg


@dataclass
class RunningServer:
    server: grpc.Server
    service: RelocalizerService
    registry: MapRegistry
    host: str
    port: int
    threads_before: tuple[int, int] | None = None  # (torch, OpenCV) counts split_threads replaced

    @property
    def address(self) -> str:
        return f"{self.host}:{self.port}"

    def stop(self, grace_s: float | None = 1.0) -> None:
        """Stop serving, and give the process back the thread counts it had before."""
        self.registry.close()
        self.server.stop(grace_s).wait()
        if self.threads_before is not None:
            set_threads(*self.threads_before)
            self.threads_before = None


def set_threads(torch_threads: int, cv2_threads: int) -> None:
    """Set torch's and OpenCV's process-wide thread counts."""
    import cv2
    import torch

    torch.set_num_threads(torch_threads)
    cv2.setNumThreads(cv2_threads)


def split_threads(workers: int) -> tuple[int, int] | None:
    """Give each of `workers` concurrent localizations its share of the cores.

    The counts are process-wide, so an embedding process gets them back from
    `RunningServer.stop`: returns the (torch, OpenCV) counts it replaced, None if it kept them.
    """
    if workers <= 1:
        return None
    import cv2
    import torch

    before = (torch.get_num_threads(), cv2.getNumThreads())
    set_threads(max(1, (os.cpu_count() or 1) // workers), 1)
    return before


def start_server(maps: dict[str, Path], config: ServeConfig = ServeConfig()) -> RunningServer:
    """Load `maps` (name -> folder), bind, start serving; returns at once."""
    config.check()
    tls = (read_tls_pair(Path(config.tls_cert), Path(config.tls_key))
           if config.tls_cert is not None else None)  # before the maps are read
    registry = MapRegistry(maps, config.load_timeout_s)
    service = RelocalizerService(registry, config)
    options = [("grpc.max_receive_message_length", config.max_request_bytes),
               ("grpc.max_send_message_length", config.max_request_bytes),
               ("grpc.so_reuseport", 0)]
    # a thread per localization, per session, per map (a ReloadMap waits for its map's one
    # load), and four for everything else (Health, ListMaps, refusals)
    pool = futures.ThreadPoolExecutor(
        config.workers + config.max_sessions + len(registry.names) + 4,
        thread_name_prefix="slamreloc-serve")
    server = grpc.server(pool, handlers=[service.handler()], options=options)
    address = f"{config.host}:{config.port}"
    if tls is not None:
        try:
            creds = grpc.ssl_server_credentials([tls])
            port = server.add_secure_port(address, creds)
        except RuntimeError as err:  # gRPC's "Failed to bind"
            raise InputError(f"cannot listen on {address} with TLS (in use, not an address of "
                             f"this machine, or a TLS pair gRPC refuses: `tls_cert` "
                             f"{config.tls_cert}, `tls_key` {config.tls_key}; gRPC: "
                             f"{' '.join(str(err).split())[:200]})") from None
    else:
        port = server.add_insecure_port(address)
    if port == 0:
        raise InputError(f"cannot listen on {address} (in use, or not an address of this "
                         "machine)")
    threads_before = split_threads(config.workers)
    server.start()
    if config.watch_s > 0:
        registry.watch(config.watch_s, lambda m: _log(f"map {quoted(m.name)} replaced on disk: "
                                                      f"now version {m.version}"))
    return RunningServer(server, service, registry, config.host, port, threads_before)


def serve_forever(maps: dict[str, Path], config: ServeConfig) -> None:
    """`slamreloc serve`: start, say where, serve until SIGINT / SIGTERM."""
    running = start_server(maps, config)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    tls = " (TLS)" if config.tls_cert else ""
    print(f"listening on {running.address}{tls} (maps: {', '.join(running.registry.names)}; "
          f"protocol {PROTOCOL})", flush=True)
    while not stop.wait(1.0):
        pass
    _log("stopping")
    running.stop(grace_s=2.0)

