"""The gRPC server of `slamreloc serve`: maps loaded once, requests on a thread pool.

Concurrency: `workers` localizations run at once (a semaphore shared by `Localize` and session
frames); with more than one, torch's threads are split between them. Every call that can wait
holds a thread of the pool, so each kind is bounded and the pool is sized for all of them at
once, which leaves threads for Health and ListMaps whatever the load: at most `max_queued`
Localize calls wait for a worker (more are refused OVERLOADED at once), none waits past its
own deadline or `queue_wait_s`, and one whose call ended meanwhile is dropped before it
computes; a session holds a thread for its lifetime (at most `max_sessions` open, and as many
opening, each within `open_timeout_s` of its SessionOpen, and cancelled after
`session_idle_s` without a message, or with an answer it leaves unread); one ReloadMap per map
waits for its load (another is refused OVERLOADED at once).

Safety: the server binds 127.0.0.1 unless told otherwise, and a non-local address needs a token
(`authorization: Bearer TOKEN` metadata, compared in constant time) or TLS with a token. Messages
are parsed here, not by gRPC, so a body that is not the method's message is a typed
`BAD_REQUEST`; one over `max_request_bytes` is refused by gRPC (RESOURCE_EXHAUSTED) before it is
read. Every refusal is a status code plus the ErrorKind's name in the `slamreloc-error`
trailing metadata; an unexpected exception is logged and answered INTERNAL, and the server
carries on. Nothing on the wire is pickled: protobuf only.
"""

from __future__ import annotations

import errno
import os
import signal
import stat
import sys
import threading
import time
import traceback
import warnings
from collections.abc import Iterator
from concurrent import futures
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import grpc
from google.protobuf.message import DecodeError

from slamreloc import __version__
from slamreloc.errors import InputError, OutOfMemory, is_out_of_memory
from slamreloc.io.address import (bind_problem, check_host, is_loopback, listen_address,
                                  port_problem)
from slamreloc.io.fileio import relation, relation_on_disk, resolved
from slamreloc.io.pem import certificates_der, read_pem
from slamreloc.map.format import META
from slamreloc.map.lock import clean_maps_folder, map_write_lock
from slamreloc.proto import PROTOCOL
from slamreloc.proto import relocalizer_pb2 as pb
from slamreloc.proto.messages import (
    ERROR_METADATA_KEY,
    TOKEN_BLANKS,
    ServiceError,
    bearer_matches,
    quoted,
    saved_map_name_problem,
    token_problem,
)
from slamreloc.service import TOKEN_ENV
from slamreloc.service.localize import localize
from slamreloc.service.maps import MapRegistry
from slamreloc.service.sessions import Session
from slamreloc.slam.live_map import LiveMapConfig

SERVICE_NAME = pb.DESCRIPTOR.services_by_name["Relocalizer"].full_name


MAX_SESSION_KEYFRAMES = 500  # a learning session's map: ~1000 rows, 3-4 MB of memory each
MIN_WATCH_S = 0.01  # the shortest `watch_s`: a check of every map folder per interval
STOP_WAIT_S = 10.0  # how long a stop waits for the calls it cancelled (seconds)
STREAMS_PER_CONNECTION = 16  # calls one connection has open at once (HTTP/2's setting)
SMALL_REQUEST_BYTES = 1 << 16  # a request this small is not counted in `max_held_bytes`


@dataclass(frozen=True)
class ServeConfig:
    host: str = "127.0.0.1"
    port: int = 50051  # 0: any free port (RunningServer.port says which)
    workers: int = 1  # localizations at once
    max_sessions: int = 8
    # of those, learning ones (no map: each learns its own, up to ~2 GB of memory when full,
    # MAX_SESSION_KEYFRAMES keyframes): the server's memory bound for learning
    max_learning_sessions: int = 2
    token: str | None = None  # required by every call when set
    tls_cert: Path | None = None  # PEM files; both or neither
    tls_key: Path | None = None
    max_request_bytes: int = 32 << 20
    # bytes of requests over SMALL_REQUEST_BYTES the server holds at once (received, queued or
    # being answered; at least one whole request whatever this says); more: OVERLOADED at once
    max_held_bytes: int = 256 << 20
    watch_s: float = 2.0  # reload maps whose folder was replaced; 0: only on ReloadMap
    load_timeout_s: float = 300.0  # a reload reading a map folder longer is refused (OVERLOADED)
    max_reloads: int = 4  # ReloadMap calls waiting for a load at once; more: OVERLOADED
    max_queued: int = 16  # Localize calls waiting for a worker; more are refused (OVERLOADED)
    queue_wait_s: float = 60.0  # the longest a call waits for a worker (less: its deadline)
    open_timeout_s: float = 10.0  # a session stream must send its SessionOpen within this
    session_idle_s: float = 600.0  # a session that sends nothing for this long is cancelled
    # the folder learning sessions save their maps into (SessionSave: DIR/NAME, then served as
    # NAME); None: a save is refused (FAILED_PRECONDITION)
    learned_maps: Path | None = None
    max_learned_maps: int = 64  # maps sessions may save under new names (each stays loaded)
    # learning sessions' maps: each grows to MAX_SESSION_KEYFRAMES keyframes at most (its
    # memory and per-frame time bounded), then tracks on in what it holds
    live: LiveMapConfig = field(
        default_factory=lambda: LiveMapConfig(max_keyframes=MAX_SESSION_KEYFRAMES))

    def check(self) -> None:
        """InputError for a configuration that must not run (a non-local bind without a token,
        half a TLS pair, a token gRPC cannot carry, out-of-range numbers)."""
        if (problem := port_problem(self.port)) is not None:
            raise problem
        if not 1 <= self.workers <= 256:
            raise InputError(f"`workers` {self.workers}: 1 to 256")
        if not 1 <= self.max_sessions <= 4096:
            raise InputError(f"`max_sessions` {self.max_sessions}: 1 to 4096")
        if not 1 <= self.max_learning_sessions <= 4096:
            raise InputError(f"`max_learning_sessions` {self.max_learning_sessions}: 1 to 4096")
        if not 1 <= self.max_learned_maps <= 4096:
            raise InputError(f"`max_learned_maps` {self.max_learned_maps}: 1 to 4096")
        if not 1 <= self.max_reloads <= 256:
            raise InputError(f"`max_reloads` {self.max_reloads}: 1 to 256")
        if not 0 <= self.max_queued <= 4096:
            raise InputError(f"`max_queued` {self.max_queued}: 0 to 4096")
        if not (1 << 16) <= self.max_held_bytes <= (64 << 30):
            raise InputError(f"`max_held_bytes` {self.max_held_bytes}: 65536 to {64 << 30}")
        if not (1 << 16) <= self.max_request_bytes <= (2 << 30) - 1:
            raise InputError(f"`max_request_bytes` {self.max_request_bytes}: 65536 to "
                             f"{(2 << 30) - 1}")
        check_seconds(self.watch_s, "watch_s", **WATCH_RULE)
        for setting in ("load_timeout_s", "queue_wait_s", "open_timeout_s", "session_idle_s"):
            check_seconds(getattr(self, setting), setting, 0.001)
        if (self.tls_cert is None) != (self.tls_key is None):
            raise InputError("`tls_cert` and `tls_key` go together")
        if self.token is not None:
            problem = token_problem(self.token)
            if problem:
                raise InputError(f"the token (`token_file` or SLAMRELOC_TOKEN) {problem}")
        if self.learned_maps is not None:
            folder = Path(self.learned_maps)
            if folder.is_symlink() or not folder.is_dir():
                what = ("a symbolic link" if folder.is_symlink() else
                        "missing" if not folder.exists() else "not a folder")
                raise InputError(f"{folder}: `learned_maps` must be an existing folder "
                                 f"(it is {what})")
            if not os.access(folder, os.W_OK | os.X_OK):
                raise InputError(f"{folder}: `learned_maps` is not writable")
        check_host(self.host)
        if not is_loopback(self.host) and self.token is None:
            raise InputError(f"`host` {self.host} is not a loopback address: anyone who reaches "
                             "it could use the server; give a token (`token_file` or "
                             "SLAMRELOC_TOKEN), and TLS (`tls_cert`/`tls_key`) off a trusted "
                             "network")


def check_seconds(seconds: float, setting: str, minimum: float, what: str = "seconds",
                  zero: str | None = None) -> None:
    """InputError naming `setting` (`what` its seconds are) unless `seconds` lies in
    [minimum, threading.TIMEOUT_MAX] (the longest wait Python's threads take; NaN fails), or
    is 0 where `zero` says what 0 means. The one rule for every interval and timeout of the
    service, command line or config."""
    if zero is not None and seconds == 0:
        return
    if not minimum <= seconds <= threading.TIMEOUT_MAX:
        off = f"0 ({zero}) or " if zero is not None else ""
        raise InputError(f"`{setting}` {seconds}: {what}, {off}{minimum:g} to "
                         f"{threading.TIMEOUT_MAX:.4g}")


WATCH_RULE = {"minimum": MIN_WATCH_S, "what": "seconds between checks of the map folders",
              "zero": "only ReloadMap"}  # `check_seconds` of `watch_s` / --watch


def read_token(token_file: Path | None, environment: bool = True) -> str | None:
    """The token from `token_file`, else (with `environment`) $SLAMRELOC_TOKEN, else None.
    One rule for every source (`serve --token-file`, the variable, a Ray Serve config's
    `token_file`): blanks around it are dropped, and an empty or blank one is an InputError
    naming its source, never "no token" (which would turn authentication off), as is one gRPC
    could not carry (`token_problem`)."""
    if token_file is not None:
        from slamreloc.io.fileio import read_text

        text = read_text(token_file, "token (`token_file`)", 1 << 16)
        source = f"{token_file}: the token (`token_file`)"
    else:
        text = os.environ.get(TOKEN_ENV) if environment else None
        source = f"the token in ${TOKEN_ENV}"
    if text is None:
        return None
    token = text.strip(TOKEN_BLANKS)
    if not token:
        raise InputError(f"{source} is empty (give a token, or leave it out to run "
                         "without one on a loopback address)")
    problem = token_problem(token)
    if problem:
        raise InputError(f"{source} {problem}")
    return token


_LOG_LOCK = threading.Lock()


def _log(message: str) -> None:
    """One line of the server's log on stderr, in one write (threads never interleave)."""
    with _LOG_LOCK:
        sys.stderr.write(f"slamreloc serve: {message}\n")
        sys.stderr.flush()


class StreamDeadlines:
    """Cancels the streams that sent nothing in time (a session's SessionOpen, its next
    message): one thread for all of them, woken every `tick_s` seconds."""

    def __init__(self, tick_s: float = 0.2):
        self.tick_s = tick_s
        self._due: dict[int, tuple[float, grpc.ServicerContext]] = {}
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="stream-deadlines", daemon=True)
        self._thread.start()

    def arm(self, key: int, seconds: float, context: grpc.ServicerContext) -> None:
        """Cancel `context` unless `disarm(key)` comes within `seconds`."""
        with self._lock:
            self._due[key] = (time.monotonic() + seconds, context)

    def disarm(self, key: int) -> None:
        with self._lock:
            self._due.pop(key, None)

    def _run(self) -> None:
        while not self._stop.wait(self.tick_s):
            now = time.monotonic()
            with self._lock:
                late = [key for key, (due, _) in self._due.items() if due <= now]
                contexts = [self._due.pop(key)[1] for key in late]
            for context in contexts:
                context.cancel()  # the stream's handler sees its requests end: it returns

    def close(self) -> None:
        self._stop.set()
        self._thread.join()


class RelocalizerService:
    """The methods of slamreloc.v1.Relocalizer over a MapRegistry."""

    def __init__(self, registry: MapRegistry, config: ServeConfig):
        self.registry, self.config = registry, config
        self.compute = threading.BoundedSemaphore(config.workers)
        # ReloadMap calls waiting for their map's load: each holds a thread of the pool, which
        # counts `max_reloads` of them (however many maps are served or saved meanwhile)
        self.reloads = threading.BoundedSemaphore(config.max_reloads)
        self.deadlines = StreamDeadlines()
        self.started = time.time()
        self._count_lock = threading.Lock()
        self.sessions = 0  # open (SessionOpen answered)
        self.opening = 0  # streams waiting for or checking their SessionOpen
        self.localizing = 0  # Localize calls running or waiting for a worker
        self.held_bytes = 0  # bytes of the requests over SMALL_REQUEST_BYTES being handled
        self.requests = 0
        self._save_lock = threading.Lock()  # one learned map written and registered at a time
        self.stopping = threading.Event()  # set by `RunningServer.stop`: no save starts writing
        self._written: set[Path] = set()  # the learned maps' folders this server wrote
        self.learning: set[Session] = set()  # learning sessions open (their learner threads)
        self.learning_opening = 0  # learning sessions whose SessionOpen is being processed
        # the learned maps' folder as it was at start-up (resolved, and its identity on disk):
        # a save writes there only while that same folder is still there
        self._learned: tuple[Path, tuple[int, int]] | None = None
        if config.learned_maps is not None:
            st = os.stat(config.learned_maps)
            self._learned = (Path(config.learned_maps).resolve(), (st.st_dev, st.st_ino))
            for name in clean_maps_folder(self._learned[0]):  # a save a killed server left
                _log(f"learned map {quoted(name)}: removed what a save cut short (a server "
                     "killed while writing it) had left beside it")

    @staticmethod
    def pool_size(config: ServeConfig) -> int:
        """Threads for every call that may wait at once - localizations and those queued for a
        worker, open and opening sessions, `max_reloads` ReloadMap calls - and four more for
        the rest (Health, ListMaps, refusals), which therefore never wait behind them."""
        return (config.workers + config.max_queued + 2 * config.max_sessions
                + config.max_reloads + 4)

    # ---- plumbing ------------------------------------------------------------------------
    @contextmanager
    def _holding(self, body: bytes) -> Iterator[None]:
        """Count a request's bytes while it is handled: OVERLOADED at once where they would
        take the requests held past `max_held_bytes` (one request is always taken, and a
        small one - Health, ListMaps, a session's save - is never counted). A request's
        memory is its bytes, the message parsed from them and, while a worker has it, the
        decoded image: many large requests at once must not take the server's memory."""
        size = len(body) if len(body) > SMALL_REQUEST_BYTES else 0
        limit = max(self.config.max_held_bytes, self.config.max_request_bytes)
        with self._count_lock:
            if size and self.held_bytes and self.held_bytes + size > limit:
                raise ServiceError(pb.OVERLOADED, f"the server holds {self.held_bytes >> 20} "
                                   f"MiB of requests, and this one's {size >> 20} MiB would "
                                   f"pass the {limit >> 20} MiB it takes at once: try again")
            self.held_bytes += size
        try:
            yield
        finally:
            with self._count_lock:
                self.held_bytes -= size

    def _refuse(self, context: grpc.ServicerContext, err: ServiceError):
        context.set_trailing_metadata(((ERROR_METADATA_KEY, err.kind_name),))
        context.abort(err.grpc_code, err.message)

    def _authorized(self, context: grpc.ServicerContext) -> bool:
        """Whether the call carries the token: exactly one `authorization` value (two are
        refused whatever their order), compared in constant time."""
        if self.config.token is None:
            return True
        return bearer_matches([v for k, v in context.invocation_metadata()
                               if k == "authorization"], self.config.token)

    def _unary(self, parse, handle):
        """A unary method: count, authenticate, parse the bytes, answer or refuse."""

        def method(body: bytes, context: grpc.ServicerContext):
            with self._count_lock:
                self.requests += 1
            try:
                if not self._authorized(context):
                    raise ServiceError(pb.UNAUTHENTICATED, "missing or wrong token")
                with self._holding(body):
                    return handle(parse_message(parse, body), context)
            except ServiceError as err:
                self._refuse(context, err)
            except Exception as err:  # noqa: BLE001 - answer, log, and keep serving
                self._refuse(context, unexpected(err))

        return method

    @contextmanager
    def _worker(self, context: grpc.ServicerContext, counted: bool) -> Iterator[None]:
        """One of the `workers` slots for a localization. `counted` (Localize): at most
        `workers + max_queued` such calls run or wait at once (OVERLOADED at once beyond;
        sessions are bounded by `max_sessions`). The wait ends at the call's deadline or after
        `queue_wait_s` (OVERLOADED), and a call that ended meanwhile (cancelled, past its
        deadline) is dropped before it computes."""
        if counted:
            with self._count_lock:
                if self.localizing >= self.config.workers + self.config.max_queued:
                    raise ServiceError(pb.OVERLOADED, f"{self.localizing} localizations running "
                                       f"or waiting for the {self.config.workers} worker(s), "
                                       "the most this server takes")
                self.localizing += 1
        try:
            self._acquire(context)
            try:
                if not context.is_active():
                    raise ServiceError(pb.OVERLOADED, "dropped: the call ended while it waited")
                yield
            finally:
                self.compute.release()
        finally:
            if counted:
                with self._count_lock:
                    self.localizing -= 1

    def _acquire(self, context: grpc.ServicerContext) -> None:
        """Take a worker slot, waiting at most until the call's deadline or `queue_wait_s`."""
        wait = self.config.queue_wait_s
        remaining = context.time_remaining()
        if remaining is not None:
            wait = min(wait, remaining)
        until = time.monotonic() + wait
        while True:
            if not context.is_active():
                raise ServiceError(pb.OVERLOADED, "dropped: the call ended (cancelled, or past "
                                   "its deadline) before a worker was free")
            left = until - time.monotonic()
            if left <= 0:
                raise ServiceError(pb.OVERLOADED, f"no worker free within {wait:.3g} s (all "
                                   f"{self.config.workers} busy)")
            if self.compute.acquire(timeout=min(left, 0.1)):  # 0.1: notice a cancel soon
                return

    # ---- methods ---------------------------------------------------------------------------
    def localize(self, request: pb.LocalizeRequest, context) -> pb.LocalizeResponse:
        served = self.registry.get(request.map)
        with self._worker(context, counted=True):
            return localize(served, request)

    def health(self, _: pb.HealthRequest, context=None) -> pb.HealthResponse:
        return pb.HealthResponse(serving=True, protocol=PROTOCOL, version=__version__,
                                 num_maps=len(self.registry.names), num_sessions=self.sessions,
                                 uptime_s=time.time() - self.started,
                                 num_requests=self.requests)

    def list_maps(self, _: pb.ListMapsRequest, context=None) -> pb.ListMapsResponse:
        return pb.ListMapsResponse(maps=[m.info() for m in self.registry.all()])

    def reload_map(self, request: pb.ReloadMapRequest, context=None) -> pb.ReloadMapResponse:
        if not self.reloads.acquire(blocking=False):
            raise ServiceError(pb.OVERLOADED, f"{self.config.max_reloads} map reloads are "
                               "running, the most this server runs at once (`max_reloads`); "
                               "try again when one is done")
        try:
            served, changed = self.registry.reload(request.map)
        finally:
            self.reloads.release()
        if changed:
            _log(f"map {quoted(served.name)} reloaded: version {served.version}")
        return pb.ReloadMapResponse(map=served.info(), changed=changed)

    def session(self, requests, context: grpc.ServicerContext):
        """Session stream: SessionOpen first (within `open_timeout_s`), then frames; ends
        with SessionClosed. Counted among the open sessions once SessionOpen is answered."""
        with self._count_lock:
            self.requests += 1
        if not self._authorized(context):
            self._refuse(context, ServiceError(pb.UNAUTHENTICATED, "missing or wrong token"))
        with self._count_lock:
            busy = max(self.sessions, self.opening)
            if busy >= self.config.max_sessions:
                self._refuse(context, ServiceError(
                    pb.OVERLOADED, f"{self.sessions} sessions open and {self.opening} opening, "
                    "the most this server takes"))
            self.opening += 1
        state = {"opened": False, "freed": False}
        key = id(state)

        def ended() -> None:  # gRPC's callback when the stream ends, however it does
            learning = state.get("session")
            if learning is not None:  # a round (a save's wait) ends at its next step
                learning.cancel()
            self._free(state)

        self.deadlines.arm(key, self.config.open_timeout_s, context)
        context.add_callback(ended)
        try:
            yield from self._session(requests, context, key, state)
        except grpc.RpcError:  # the stream was cancelled (by the client, or a deadline)
            if context.is_active():
                raise
        finally:
            self.deadlines.disarm(key)
            learning = state.get("session")
            if learning is not None:  # its training round ends before its thread is let go
                learning.release()
                with self._count_lock:
                    self.learning.discard(learning)
            self._free(state)

    def _reserve_learning(self, state: dict) -> None:
        """Hold a learning session's place while it opens (OVERLOADED when
        `max_learning_sessions` are open or opening: the server's memory bound for learning);
        given back once it is open or refused (`_unreserve_learning`)."""
        with self._count_lock:
            busy = len(self.learning) + self.learning_opening
            if busy >= self.config.max_learning_sessions:
                instead = "open one with a map, or retry" if self.registry.names else "retry"
                raise ServiceError(pb.OVERLOADED, f"{busy} learning sessions open, the most "
                                   "this server takes (each may hold about 2 GB while it "
                                   "learns; one that has ended gives its place back when its "
                                   f"training round stops, within seconds); {instead} later")
            self.learning_opening += 1
            state["reserved"] = True

    def _unreserve_learning(self, state: dict, opened: Session | None = None) -> None:
        """Give the place `_reserve_learning` held back; `opened`: the learning session that
        took it, counted among `learning` in the same step (no other open slips between)."""
        with self._count_lock:
            if opened is not None:
                self.learning.add(opened)
            if state.get("reserved"):
                state["reserved"] = False
                self.learning_opening -= 1

    def _free(self, state: dict) -> None:
        """Give a session's slot back, once: when its stream ends (a client that leaves frees
        it at once, even while the handler still waits on a training round) or its handler
        returns, whichever comes first."""
        self._unreserve_learning(state)  # a learning session that never opened
        with self._count_lock:
            if state["freed"]:
                return
            state["freed"] = True
            if state["opened"]:
                self.sessions -= 1
            else:
                self.opening -= 1

    def _opened(self, state: dict) -> None:
        """Count a session as open (OVERLOADED when `max_sessions` already are)."""
        with self._count_lock:
            if state["freed"]:  # the stream ended while its SessionOpen was processed
                raise ServiceError(pb.FAILED_PRECONDITION, "the session's stream has ended")
            if self.sessions >= self.config.max_sessions:
                raise ServiceError(pb.OVERLOADED, f"{self.sessions} sessions open, the most "
                                   "this server takes")
            self.opening -= 1
            self.sessions += 1
            state["opened"] = True

    def _open_session(self, msg: pb.SessionRequest, kind: str | None, state: dict) -> Session:
        """The session a stream's first message opens (its SessionOpen), counted as open."""
        if kind != "open":
            raise ServiceError(pb.BAD_REQUEST, "a session starts with SessionOpen, got "
                               f"{_session_message(kind)}")
        learn = msg.open.learn or (not msg.open.map and not self.registry.names)
        if learn and msg.open.map:
            raise ServiceError(pb.BAD_REQUEST, "open.learn: a learning session starts with no "
                               f"map, got map {quoted(msg.open.map)}")
        if learn:
            self._reserve_learning(state)
        try:
            session = Session(None if learn else self.registry.get(msg.open.map), msg.open,
                              self.config.live)
            self._opened(state)
        except BaseException:
            self._unreserve_learning(state)
            raise
        if session.learning:
            state["session"] = session
            self._unreserve_learning(state, opened=session)
        return session

    def _session(self, requests, context, key: int, state: dict):
        session = None
        for body in requests:
            self.deadlines.disarm(key)  # a message: no deadline while it is processed
            try:
                with self._holding(body):  # a frame's bytes count while it is handled
                    msg = parse_message(pb.SessionRequest, body)
                    kind = msg.WhichOneof("message")
                    if session is None:
                        session = self._open_session(msg, kind, state)
                        update = pb.SessionUpdate(opened=session.opened())
                    elif kind == "save":  # no worker slot: a save computes no localization
                        update = pb.SessionUpdate(saved=self._save(session, msg.save, context))
                    elif kind != "frame":
                        raise ServiceError(pb.BAD_REQUEST, "a frame expected, got "
                                           f"{_session_message(kind)}")
                    else:
                        with self._worker(context, counted=False):
                            update = pb.SessionUpdate(frame=session.frame(msg.frame))
            except ServiceError as err:
                if session is None:  # nothing to carry on with
                    self._refuse(context, err)
                update = pb.SessionUpdate(error=pb.SessionError(
                    kind=err.kind, message=err.message, frame=session.n_frames))
            except Exception as err:  # noqa: BLE001
                refusal = unexpected(err)
                if session is None:
                    self._refuse(context, refusal)
                update = pb.SessionUpdate(error=pb.SessionError(
                    kind=refusal.kind, message=refusal.message, frame=session.n_frames))
            finally:  # armed before the answer is sent: a client that never reads its answers
                # (the send blocks) is cancelled as one that sends nothing
                self.deadlines.arm(key, self.config.session_idle_s if session is not None
                                   else self.config.open_timeout_s, context)
            yield update.SerializeToString()
        self.deadlines.disarm(key)  # closing: no deadline while the trajectory is made
        if session is not None and context.is_active():
            try:
                with self._worker(context, counted=False):
                    update = pb.SessionUpdate(closed=session.close())
            except ServiceError as err:  # no worker came (or the client left): said so
                if not context.is_active():
                    return
                update = pb.SessionUpdate(error=pb.SessionError(
                    kind=err.kind, message=f"close: {err.message}", frame=session.n_frames))
            # the last answer too: a client that never reads it is cancelled after
            # `session_idle_s`, its slot given back
            self.deadlines.arm(key, self.config.session_idle_s, context)
            yield update.SerializeToString()

    def _save(self, session: Session, request: pb.SessionSave,
              context: grpc.ServicerContext | None = None) -> pb.MapSaved:
        """Write a learning session's map into `learned_maps`/NAME and serve it as NAME (added,
        or swapped in where this server already serves NAME from there). Refused: a session
        that learns nothing, a server without `learned_maps`, a NAME that is not a plain map
        name (`saved_map_name_problem`), a target the server may not write (`_target_problem`),
        a map before the first training round has ended, another session's save being written
        (OVERLOADED at once: the save lock is never waited for), a file system error (one
        line, no server path: `save_refusal`), something in the way that the map writer
        does not take for its own (`_writer_refusal`).

        The training round the save waits for (up to 2 x `Session.SAVE_WAIT_S`) runs on the
        session's own learner and holds neither a worker slot nor the save lock: Localize,
        other sessions' frames and saves, Health and ListMaps go on meanwhile. The lock is
        held only to check the target again (under the map's write lock, as found after a
        killed writer's clean-up), write the map and register it."""
        if not session.learning:
            raise ServiceError(pb.FAILED_PRECONDITION, "save: this session tracks in a served "
                               "map and learns none (open it with SessionOpen.learn)")
        if self.config.learned_maps is None:
            raise ServiceError(pb.FAILED_PRECONDITION, "save: this server keeps no learned "
                               "maps (its operator did not give `--learned-maps DIR`)")
        name = request.name
        problem = saved_map_name_problem(name)
        if problem:
            raise ServiceError(pb.BAD_REQUEST, f"save.name {quoted(name)} {problem}")
        try:
            path = self._learned[0] / name
            self._check_target(name, path)  # before the wait: a refusal needs no round
            session.train_for_save()
            if context is not None and not context.is_active():  # the client left meanwhile
                raise ServiceError(pb.FAILED_PRECONDITION, f"save.name {quoted(name)}: the "
                                   "session's stream ended before its round did; nothing was "
                                   "written")
            if not self._save_lock.acquire(blocking=False):
                raise ServiceError(pb.OVERLOADED, f"save.name {quoted(name)}: another "
                                   "session's map is being written; try again when it is done")
            try:
                if self.stopping.is_set():  # a save either ends written and logged, or not begun
                    raise ServiceError(pb.FAILED_PRECONDITION, f"save.name {quoted(name)}: "
                                       "the server is stopping; nothing was written")
                # again, under the map's write lock: the maps may have changed meanwhile,
                # and a map a killed writer had moved aside is put back, then checked
                with map_write_lock(path):
                    self._check_target(name, path)
                    saved = session.write(path)
                if saved is None:
                    live = session.live_map
                    raise ServiceError(pb.FAILED_PRECONDITION, f"save.name {quoted(name)}: no "
                                       f"map yet: the session has labelled {live.store.n_rows} "
                                       "keypoints with depth, and a map needs a training "
                                       f"round on {live.config.learner.min_rows} or more")
                self._written.add(path)
                served = self.registry.register(name, path)
            finally:
                self._save_lock.release()
        except OSError as err:
            raise save_refusal(name, err) from None
        except InputError as err:  # the map writer's refusal of what is in the way
            raise self._writer_refusal(name, err) from None
        _log(f"map {quoted(name)} saved by session {session.id}: version {served.version}")
        saved.name, saved.map_version = name, served.version
        saved.num_points = served.scene_map.info.n_labelled
        return saved

    def _writer_refusal(self, name: str, err: InputError) -> ServiceError:
        """FAILED_PRECONDITION for a save the map writer refused (something in the way in the
        learned maps' folder that is not the writer's: a link or a user's file at its lock, a
        folder at its temporary name, other files in the map's folder): its reason, paths
        given relative to that folder (never the server's own), the whole line logged."""
        _log(f"map {quoted(name)} not saved: {err}")
        folder = str(self._learned[0])
        reason = str(err).replace(folder + os.sep, "").replace(folder, "the folder")
        return ServiceError(pb.FAILED_PRECONDITION, f"save.name {quoted(name)}: nothing was "
                            f"written: in the server's folder of learned maps, {reason}; ask "
                            "its operator")

    def _check_target(self, name: str, path: Path) -> None:
        """ServiceError FAILED_PRECONDITION unless a save may write the map NAME at `path`
        (`learned_maps`/NAME, resolved): NAME is not served from another folder; `path` is
        not, does not hold and does not lie inside the folder of a map served under another
        name, nor an input a served map records (its dataset, its pose file); it is absent, or
        a map this server serves as NAME (given as MAP, or saved before) or wrote itself - a
        map left in the folder by an earlier run or another server is not replaced (give it as
        MAP to save over it); never a symbolic link nor anything that is not a map. A served
        map's folder is the one it was loaded from (`ServedMap.folder`), whatever links were
        made on disk since (a reload refuses them: `MapRegistry._check_folder`)."""
        said = f"save.name {quoted(name)}"
        problem = self._learned_folder_problem()
        if problem:
            _log(f"map {quoted(name)} not saved: {self.config.learned_maps} {problem}")
            raise ServiceError(pb.FAILED_PRECONDITION, f"{said}: the server's folder of "
                               f"learned maps {problem}; ask its operator")
        maps = self.registry.all()
        own = False  # NAME is served from `path`
        for m in maps:
            folder = m.folder or resolved(m.path)  # the folder it is served from (loaded)
            if m.name == name:
                if folder != path:
                    raise ServiceError(pb.FAILED_PRECONDITION, f"{said}: a map of that name is "
                                       "served from elsewhere; choose another name")
                own = True
            elif how := relation(path, folder):
                raise ServiceError(pb.FAILED_PRECONDITION, f"{said}: its folder "
                                   f"{how} the folder of the map "
                                   f"{quoted(m.name)} this server serves; choose another name")
        for m in maps:
            try:
                recorded = m.scene_map.info.recorded_inputs()
            except InputError:
                recorded = {"an input the map records (unreadable)": m.path}
            for what, source in recorded.items():
                how = None if source is None else relation(path, resolved(source))
                if how:
                    raise ServiceError(pb.FAILED_PRECONDITION, f"{said}: its folder "
                                       f"{how} {what} (map "
                                       f"{quoted(m.name)}); choose another name")
        if path.is_symlink() or (os.path.lexists(path) and not (path / META).is_file()):
            what = ("a symbolic link (never written through)" if path.is_symlink()
                    else "something that is not a map")
            raise ServiceError(pb.FAILED_PRECONDITION, f"{said}: the learned maps' folder "
                               f"holds {what} of that name; choose another name")
        if os.path.lexists(path) and not own and path not in self._written:
            raise ServiceError(pb.FAILED_PRECONDITION, f"{said}: the learned maps' folder "
                               "holds a map of that name that this server does not serve "
                               "(left by an earlier run or another server); the operator gives "
                               "it as MAP to serve it and save over it, or choose another name")
        saved = {p for p in self._written if p != path}
        if not own and len(saved) >= self.config.max_learned_maps:
            raise ServiceError(pb.OVERLOADED, f"{said}: this server already serves "
                               f"{len(saved)} maps its sessions saved, the most it keeps "
                               "(`max_learned_maps`: each stays loaded); save over one of them")

    def finish_saves(self) -> None:
        """From now on no save begins writing; one that is writing is waited for (the save
        lock is held only while a map is written and registered); the training rounds of
        learning sessions end at their next step (a save waiting on one is then refused)."""
        self.stopping.set()
        with self._count_lock:
            learning = list(self.learning)
        for session in learning:
            session.cancel()
        with self._save_lock:
            pass

    def _learned_folder_problem(self) -> str | None:
        """Why the learned maps' folder can no longer take a save, or None: it must be the very
        folder the server started with (not removed, nor replaced by another folder, a link
        or a file: a save never writes elsewhere, nor re-creates it)."""
        folder = Path(self.config.learned_maps)
        try:
            st = os.lstat(folder)
        except FileNotFoundError:
            return "was removed since the server started"
        except OSError as err:
            return f"cannot be read ({err.strerror or type(err).__name__})"
        if stat.S_ISLNK(st.st_mode):
            return "was replaced by a symbolic link since the server started"
        if not stat.S_ISDIR(st.st_mode):
            return "was replaced by something that is not a folder since the server started"
        if (st.st_dev, st.st_ino) != self._learned[1]:
            return "was replaced by another folder since the server started"
        return None

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


def _session_message(kind: str | None) -> str:
    """A SessionRequest's content, in words, for a refusal."""
    return {"open": "a second SessionOpen", "frame": "a frame", "save": "a SessionSave",
            None: "an empty SessionRequest (neither open, frame nor save)"}.get(kind, str(kind))


def save_refusal(name: str, err: OSError) -> ServiceError:
    """The refusal of a save the server's file system refused: one line naming the save and
    the system's reason, never a server path (logged, with it, for the operator):
    BAD_REQUEST for a name too long for that file system, else FAILED_PRECONDITION."""
    _log(f"map {quoted(name)} not saved: {type(err).__name__}: {' '.join(str(err).split())}")
    reason = err.strerror or type(err).__name__
    kind = pb.BAD_REQUEST if err.errno == errno.ENAMETOOLONG else pb.FAILED_PRECONDITION
    return ServiceError(kind, f"save.name {quoted(name)}: the server's file system refused "
                        f"the map ({reason}); choose another name or ask its operator")


def learned_maps_problem(folder: Path, maps: list) -> str | None:
    """Why `folder` cannot be `learned_maps` beside the served `maps` (ServedMap), or None: it
    must not be, nor lie inside, a served map's folder, nor an input a served map records
    (its dataset, its pose file: `MapMeta.recorded_inputs`), where a session's save would
    write. A served map may lie inside it (a map saved there and served again by name)."""
    where = resolved(folder)
    for m in maps:
        inputs = {f"the folder of the served map {quoted(m.name)}": m.path}
        inputs.update({f"{what} (map {quoted(m.name)})": p
                       for what, p in m.scene_map.info.recorded_inputs().items()})
        for what, p in inputs.items():
            if p is None:
                continue
            how = relation_on_disk(where, resolved(p))  # a bind mount is the same folder
            if how in ("is", "lies inside"):
                said = what if how == "is" else f"{what}, {p}"
                return (f"{folder}: `learned_maps` {how} {said}: a "
                        "session's save would write there; give a folder of its own")
    return None


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
    out = []
    for path, option, what in ((key, "tls_key", "private key"),
                               (cert, "tls_cert", "certificate")):
        out.append(read_pem(path, what, option))
    problem = pair_problem(out[0], out[1])
    if problem:
        raise InputError(f"{key}: `tls_key` does not belong to the certificate in {cert} "
                         f"(`tls_cert`): {problem}")
    problem = certificate_problem(out[1]) or handshake_problem(out[0], out[1])
    if problem:
        raise InputError(f"{cert}: `tls_cert` cannot serve TLS: {problem}")
    return out[0], out[1]


def handshake_problem(key: bytes, cert: bytes) -> str | None:
    """Why a client trusting the top of the PEM chain (its last certificate, or the server's
    own certificate where that signed itself) refuses the chain, found by a TLS handshake
    in memory through OpenSSL's verifier (what the C++ client runs; its path rules are those
    of RFC 5280: every issuer a CA, path lengths, name constraints, extended key usage along
    the chain), or None (also None where no such top is at hand: one certificate that another
    signed, the last of several out of its dates, or no memfd to hold the key). The host name
    is not checked: clients may reach the server under any of its names."""
    import ssl
    from datetime import datetime, timezone

    try:
        from cryptography import x509
        from cryptography.hazmat.primitives.serialization import Encoding

        chain = [x509.load_der_x509_certificate(der) for der in certificates_der(cert)]
    except Exception:  # noqa: BLE001 - no cryptography; or parsed by pem_problem already
        return None
    now = datetime.now(timezone.utc)
    top = chain[-1] if len(chain) > 1 or chain[0].issuer == chain[0].subject else None
    if len(chain) > 1 and not top.not_valid_before_utc <= now <= top.not_valid_after_utc:
        top = chain[-2] if len(chain) > 2 else None  # a cross-signed root, warned of
    if top is None or not hasattr(os, "memfd_create"):
        return None
    try:  # OpenSSL reads them as written here: never the user's bytes, never a pass phrase
        from cryptography.hazmat.primitives import serialization

        clean_key = serialization.load_pem_private_key(key, password=None).private_bytes(
            Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption())
    except Exception:  # noqa: BLE001 - parsed by pem_problem already
        return None
    clean_chain = b"".join(one.public_bytes(Encoding.PEM) for one in chain)
    server = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    client = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
    server.set_ciphers("DEFAULT:@SECLEVEL=0")  # it presents whatever it has; the client judges
    client.set_ciphers(f"DEFAULT:@SECLEVEL={TLS_SECURITY_LEVEL}")
    client.check_hostname = False
    client.verify_flags |= ssl.VERIFY_X509_PARTIAL_CHAIN  # the top need not sign itself
    client.load_verify_locations(cadata=top.public_bytes(Encoding.DER))
    files = [os.memfd_create(name) for name in ("tls_cert", "tls_key")]  # never on a disk
    try:
        for descriptor, data in zip(files, (clean_chain, clean_key)):
            os.write(descriptor, data)
        try:
            server.load_cert_chain(*(f"/proc/self/fd/{d}" for d in files), password=b"")
        except (ssl.SSLError, OSError):
            return None  # gRPC reads it (pair_problem has compared the keys): let it say
        return _memory_handshake(server, client)
    finally:
        for descriptor in files:
            os.close(descriptor)


def _memory_handshake(server, client) -> str | None:
    """Run a TLS handshake between two ssl contexts over memory buffers; why the client
    refused the server's certificate chain, or None."""
    import ssl

    to_server, to_client = ssl.MemoryBIO(), ssl.MemoryBIO()
    ends = [client.wrap_bio(to_client, to_server, server_side=False),
            server.wrap_bio(to_server, to_client, server_side=True)]
    done = [False, False]
    for _ in range(20):  # TLS 1.3 takes 1.5 round trips; a bound all the same
        for i, end in enumerate(ends):
            if done[i]:
                continue
            try:
                end.do_handshake()
                done[i] = True
            except ssl.SSLWantReadError:
                pass
            except ssl.SSLCertVerificationError as err:
                return (f"clients refuse its chain ({err.verify_message}; OpenSSL's "
                        "verifier, trusting the chain's last certificate)")
            except ssl.SSLError as err:
                if i == 1:  # the server saw the client's alert: the client's reason came first
                    continue
                return f"a TLS handshake with it fails ({err.reason or err})"
        if all(done):
            return None
    return None


# OpenSSL's security level the start-up handshake verifies the chain at (`handshake_problem`):
# level 2 refuses MD5 and SHA-1 signatures and RSA keys under 2048 bits anywhere in the chain,
# as the C++ client's OpenSSL does (gRPC's BoringSSL in the Python client takes them)
TLS_SECURITY_LEVEL = 2
TLS_CURVES = ("secp256r1", "secp384r1")  # the ECDSA curves gRPC's TLS (BoringSSL) signs with
MIN_RSA_BITS = 2048


def certificate_problem(cert: bytes, now=None) -> str | None:
    """Why no client could complete a TLS handshake with the PEM certificate chain (the server's
    certificate first), or None (also None without the `cryptography` package to tell): any
    certificate of the chain not yet valid or expired (at `now`, a UTC datetime, default the
    present; the last of several only warned of: it may be a cross-signed root that clients
    trusting the root never use) or marking critical an extension TLS verifiers do not handle
    (`TLS_CRITICAL_EXTENSIONS`), any after the first that may not sign certificates (a
    version 3 certificate without basicConstraints CA:TRUE, a key usage without
    keyCertSign); the server's own certificate with a key usage that allows no
    signature (every TLS key exchange here is signed: ECDHE) or an extended key usage without
    serverAuth, an RSA key under MIN_RSA_BITS or one for RSA-PSS only, an ECDSA key on a curve
    other than TLS_CURVES or given by explicit parameters, another key type (DSA, EdDSA)."""
    try:
        from datetime import datetime, timezone

        from cryptography import x509
        from cryptography.hazmat.primitives.asymmetric import ec, rsa
        from cryptography.x509.oid import ExtendedKeyUsageOID, PublicKeyAlgorithmOID
    except ImportError:
        return None
    try:
        chain = [x509.load_der_x509_certificate(der) for der in certificates_der(cert)]
        leaf = chain[0]
        key = leaf.public_key()
        algorithm = leaf.public_key_algorithm_oid
    except Exception:  # noqa: BLE001 - parsed by pem_problem already
        return None
    now = now or datetime.now(timezone.utc)
    for number, one in enumerate(chain, 1):
        which = "" if number == 1 else f"certificate {number} of its chain "
        dates = (f"{which and which + 'is '}not valid before "
                 f"{one.not_valid_before_utc:%Y-%m-%d %H:%M} UTC"
                 if now < one.not_valid_before_utc else
                 f"{which}expired on {one.not_valid_after_utc:%Y-%m-%d %H:%M} UTC"
                 if now > one.not_valid_after_utc else None)
        if dates and 1 < number == len(chain):  # perhaps a cross-signed root (AddTrust)
            warnings.warn(f"`tls_cert`: {dates}; a client that trusts its subject as a root "
                          "stops before it, any other refuses the chain", stacklevel=2)
        elif dates:
            return dates
        try:
            unknown = [e.oid.dotted_string for e in one.extensions
                       if e.critical and e.oid.dotted_string not in TLS_CRITICAL_EXTENSIONS]
        except Exception as err:  # noqa: BLE001 - an extension cryptography cannot parse
            return f"{which or 'it '}cannot be read ({' '.join(str(err).split())[:120]})"
        if unknown:
            return (f"{which or 'it '}marks critical an extension TLS clients do not handle "
                    f"({', '.join(unknown)[:120]}), so they refuse it")
        if number > 1:  # it signs the one before it: a CA's
            limits = _extension(one, x509.BasicConstraints)
            if one.version == x509.Version.v3 and (limits is None or not limits.ca):
                return (f"{which}may not sign certificates (its basicConstraints do not say "
                        "CA:TRUE), so clients refuse the chain")
            usage = _extension(one, x509.KeyUsage)
            if usage is not None and not usage.key_cert_sign:
                return (f"{which}may not sign certificates (its key usage does not allow "
                        "keyCertSign), so clients refuse the chain")
    usage = _extension(leaf, x509.KeyUsage)
    if usage is not None and not usage.digital_signature:
        return ("its key usage (keyUsage) does not allow digitalSignature, which every TLS "
                "handshake here needs (its key signs the key exchange)")
    purposes = _extension(leaf, x509.ExtendedKeyUsage)
    if purposes is not None and not {ExtendedKeyUsageOID.SERVER_AUTH,
                                     ExtendedKeyUsageOID.ANY_EXTENDED_KEY_USAGE} & set(purposes):
        names = ", ".join(getattr(o, "_name", o.dotted_string) for o in purposes)
        return (f"its extended key usage allows only {names[:120]}, not serverAuth (a TLS "
                "server's), so clients refuse it")
    wanted = f"RSA (at least {MIN_RSA_BITS} bits) or ECDSA ({' or '.join(TLS_CURVES)}) keys"
    if algorithm == PublicKeyAlgorithmOID.RSASSA_PSS:
        return (f"its key is for RSA-PSS only, which gRPC's TLS does not take: TLS here takes "
                f"{wanted}")
    if isinstance(key, rsa.RSAPublicKey):
        if key.key_size < MIN_RSA_BITS:
            return f"an RSA key of {key.key_size} bits (at least {MIN_RSA_BITS})"
        return None
    if isinstance(key, ec.EllipticCurvePublicKey):
        if key.curve.name not in TLS_CURVES:
            return (f"an ECDSA key on curve {key.curve.name}, which TLS here does not sign with "
                    f"({' or '.join(TLS_CURVES)})")
        if _explicit_curve(leaf.tbs_certificate_bytes):
            return ("its ECDSA key gives its curve by explicit parameters, which gRPC's TLS "
                    "does not take: write the key with the curve's name "
                    f"({' or '.join(TLS_CURVES)})")
        return None
    return (f"its key is {type(key).__name__.replace('PublicKey', '').lstrip('_')}: TLS here takes "
            f"{wanted}")


# Extensions that TLS verifiers (OpenSSL, BoringSSL) handle when marked critical: any other
# critical extension makes them refuse the certificate (RFC 5280, 4.2)
TLS_CRITICAL_EXTENSIONS = frozenset({
    "2.5.29.19",  # basicConstraints
    "2.5.29.15",  # keyUsage
    "2.5.29.37",  # extendedKeyUsage
    "2.5.29.17",  # subjectAltName
    "2.5.29.30",  # nameConstraints
    "2.5.29.32",  # certificatePolicies
    "2.5.29.33",  # policyMappings
    "2.5.29.36",  # policyConstraints
    "2.5.29.54",  # inhibitAnyPolicy
})


def _extension(cert, kind):
    """The value of the certificate's extension of class `kind`, or None where it has none."""
    from cryptography import x509

    try:
        return cert.extensions.get_extension_for_class(kind).value
    except x509.ExtensionNotFound:
        return None


def _explicit_curve(tbs: bytes) -> bool:
    """Whether the certificate's key (its DER tbsCertificate) gives its algorithm's parameters
    as a SEQUENCE (an ECDSA curve by explicit parameters) rather than a curve's OID."""

    def element(at: int) -> tuple[int, int]:  # (where its value starts, where it ends)
        size = tbs[at + 1]
        if size < 0x80:
            return at + 2, at + 2 + size
        n = size & 0x7F
        return at + 2 + n, at + 2 + n + int.from_bytes(tbs[at + 2:at + 2 + n], "big")

    try:
        at = element(0)[0]  # into tbsCertificate
        if tbs[at] == 0xA0:  # [0] version
            at = element(at)[1]
        for _ in range(5):  # serialNumber, signature, issuer, validity, subject
            at = element(at)[1]
        algorithm = element(at)[0]  # subjectPublicKeyInfo -> its AlgorithmIdentifier
        after_oid = element(element(algorithm)[0])[1]
        return tbs[after_oid] == 0x30
    except IndexError:
        return False


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
        leaf = x509.load_der_x509_certificate(certificates_der(cert)[0]).public_key()
        fmt = (serialization.Encoding.PEM, serialization.PublicFormat.SubjectPublicKeyInfo)
        if public.public_bytes(*fmt) != leaf.public_bytes(*fmt):
            return "their public keys differ"
    except Exception:  # noqa: BLE001 - parsed above; an exotic key type: let gRPC say
        return None
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
        return listen_address(self.host, self.port)

    def stop(self, grace_s: float | None = 1.0) -> bool:
        """Stop serving - the watch and any map load too, waited for - and give the process
        back the thread counts it had before. A learned map being written is finished (and
        logged) first; a save that has not begun writing is refused. Calls still running
        after `grace_s` are cancelled, and waited for STOP_WAIT_S more: returns whether they
        all ended (False: some thread of gRPC's still holds one, logged)."""
        self.service.finish_saves()
        self.registry.close()
        ended = self.server.stop(grace_s).wait((grace_s or 0.0) + STOP_WAIT_S)
        if not ended:
            _log(f"calls still running {(grace_s or 0.0) + STOP_WAIT_S:g} s after the stop "
                 "were left behind")
        self.service.deadlines.close()
        with self.service._count_lock:
            learning = list(self.service.learning)
        for session in learning:  # no learner thread outlives the server
            session.release()
        if self.threads_before is not None:
            set_threads(*self.threads_before)
            self.threads_before = None
        return ended


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
    problem = bind_problem(config.host, config.port)  # before gRPC logs its own lines
    if problem is not None:
        raise problem
    registry = MapRegistry(maps, config.load_timeout_s)
    if config.learned_maps is not None:
        try:
            problem = learned_maps_problem(Path(config.learned_maps), registry.all())
        except InputError:
            registry.close()
            raise
        if problem is not None:
            registry.close()
            raise InputError(problem)
    service = RelocalizerService(registry, config)
    # only what is received is bounded: an answer (a long session's trajectory, the list of
    # many maps) is the server's own and must reach the client whole
    options = [("grpc.max_receive_message_length", config.max_request_bytes),
               ("grpc.max_send_message_length", -1),
               ("grpc.so_reuseport", 0),
               # a call waiting for a thread buffers no more than HTTP/2's first window (64
               # KiB), not a window grown to megabytes by bandwidth probes: the bytes of the
               # requests received stay those the handlers hold (`max_held_bytes`)
               ("grpc.http2.bdp_probe", 0),
               # a client's calls beyond these wait on its side of the connection, not here
               ("grpc.max_concurrent_streams", STREAMS_PER_CONNECTION)]
    pool = futures.ThreadPoolExecutor(RelocalizerService.pool_size(config),
                                      thread_name_prefix="slamreloc-serve")
    server = grpc.server(pool, handlers=[service.handler()], options=options)
    address = listen_address(config.host, config.port)
    try:
        port = (server.add_secure_port(address, grpc.ssl_server_credentials([tls]))
                if tls is not None else server.add_insecure_port(address))
    except RuntimeError as err:  # gRPC's "Failed to bind": taken since bind_problem looked
        port, reason = 0, " ".join(str(err).split())[:200]
    else:
        reason = "in use, or not an address of this machine"
    if port == 0:
        registry.close()
        service.deadlines.close()
        if tls is not None and _listens_without_tls(address):  # the pair, not the address
            raise InputError(f"{config.tls_cert}: `tls_cert` (with `tls_key` {config.tls_key}) "
                             f"is a TLS pair gRPC refuses: it listens on {address} without "
                             f"TLS, not with this pair ({reason})")
        raise InputError(f"`port` {config.port} / `host` {quoted(config.host)}: cannot listen "
                         f"on {address} ({reason})")
    threads_before = split_threads(config.workers)
    server.start()
    if config.watch_s > 0:
        registry.watch(config.watch_s, lambda m: _log(f"map {quoted(m.name)} replaced on disk: "
                                                      f"now version {m.version}"),
                       lambda message: _log(f"warning: {message}"))
    return RunningServer(server, service, registry, config.host, port, threads_before)


def _listens_without_tls(address: str) -> bool:
    """Whether a server may listen on `address` without TLS (tried, then closed at once)."""
    probe = grpc.server(futures.ThreadPoolExecutor(1), options=[("grpc.so_reuseport", 0)])
    try:
        return probe.add_insecure_port(address) != 0
    except RuntimeError:
        return False
    finally:
        probe.stop(None)


def serve_forever(maps: dict[str, Path], config: ServeConfig) -> None:
    """`slamreloc serve`: start, say where, serve until SIGINT / SIGTERM."""
    from slamreloc.runtime.memory import limit_malloc_arenas

    limit_malloc_arenas()  # before the pool's threads: each would reserve 64 MB of its own
    running = start_server(maps, config)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    tls = " (TLS)" if config.tls_cert else ""
    learned = (f"; learned maps saved in {config.learned_maps}" if config.learned_maps
               else "")
    print(f"listening on {running.address}{tls} (maps: {', '.join(running.registry.names)}"
          f"{learned}; "
          f"protocol {PROTOCOL})", flush=True)
    while not stop.wait(1.0):
        pass
    _log("stopping")
    if not running.stop(grace_s=2.0):  # a call gRPC never ended: its thread would hold the
        sys.stdout.flush()  # interpreter's exit, which joins every thread, for ever
        sys.stderr.flush()
        os._exit(0)

