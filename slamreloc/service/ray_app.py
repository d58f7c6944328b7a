"""What runs inside Ray Serve for `slamreloc serve --engine ray` (the driver that starts it:
`slamreloc.service.ray_serve`).

Layout: one Serve application (`APP_NAME`) whose ingress is a `Router` deployment that
implements the unary RPCs (Localize, Health, ListMaps, ReloadMap) behind Serve's gRPC proxy,
and one `MapReplica` deployment per map with `replicas` replicas. Each map replica loads its map
once (`ServedMap.load`, via `MapRegistry`), answers `localize` for it, and watches its folder
like the native server's `--watch` (a folder replaced on disk is swapped in atomically; requests
in flight finish on the map they started with). The router holds one DeploymentHandle per map
and routes a `LocalizeRequest` by its `map` field ("" names the only map of a deployment with
one); Serve balances a map's requests over its replicas. With one application a client needs no
`application` metadata; next to other Serve applications it sends
`("application", APP_NAME)`.

Errors are the native server's: a refused request comes back as the status code of
`slamreloc.proto.messages.GRPC_CODES` (via `ServiceError.grpc_code`) with the ErrorKind's name
in the `slamreloc-error` trailing metadata, set on Serve's `RayServegRPCContext`.

What crosses Ray's internal transport (between Ray's own processes, which trust each other:
run Ray on a trusted network only):
  * client -> Serve's gRPC proxy: protobuf (the only client wire); the proxy parses the request
    with the generated deserializer and hands the message object to the router replica, which
    Ray pickles (a protobuf message pickles as its serialized bytes);
  * router -> map replica: the request's protobuf bytes (`SerializeToString`), never objects;
  * map replica -> router: a tuple `(error_kind, payload)`: 0 and the `LocalizeResponse`'s
    protobuf bytes, or an ErrorKind value and the UTF-8 message; `MapInfo` as protobuf bytes;
  * router -> proxy -> client: the response message, serialized by Serve to protobuf.
Ray serializes these tuples and arguments with its own (pickle-based) serialization.

Not on Ray: the `Session` stream (refused FAILED_PRECONDITION). Serve 2.60's proxy does forward
bidirectional streams (`gRPCInputStream`, beta), but a session is stateful (SLAM backend and
pose graph) and all its frames must reach the one process that holds it; a DeploymentHandle
cannot stream requests from the router to one map replica, so sessions stay with
`slamreloc serve --engine grpc`.

Binding: Serve's gRPC proxy listens on all interfaces (`[::]:PORT`) whatever `host` says
(`host` binds only Serve's HTTP proxy, which this application does not use); give a `token`
(`authorization: Bearer TOKEN` metadata, checked by the router) or firewall the port.
"""

from __future__ import annotations

import re
import sys
import time
import traceback
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ray import serve
from ray.serve.grpc_util import RayServegRPCContext

from slamreloc import __version__
from slamreloc.errors import InputError
from slamreloc.io.fileio import resolved
from slamreloc.io.limits import InputLimits
from slamreloc.proto import PROTOCOL
from slamreloc.proto import relocalizer_pb2 as pb
from slamreloc.proto.messages import (
    ERROR_METADATA_KEY,
    ServiceError,
    bearer_matches,
    map_name_problem,
    quoted,
    token_problem,
)
from slamreloc.service import MAX_REPLICAS
from slamreloc.service.server import WATCH_RULE, check_seconds, read_token

if TYPE_CHECKING:
    from ray.serve.deployment import Application
    from ray.serve.handle import DeploymentHandle

APP_NAME = "slamreloc"
# Serve routes gRPC only to applications with a route prefix (HTTP to it finds no handler)
ROUTE_PREFIX = "/slamreloc"
SERVICER_FUNCTION = "slamreloc.proto.relocalizer_pb2_grpc.add_RelocalizerServicer_to_server"
REPLICA_CPUS = 0.25  # Ray CPUs reserved per map replica (fractional: several share a core)
MIN_REPLICA_CPUS = 0.01  # the least a replica may reserve (Ray refuses far smaller shares)
ROUTER_CPUS = 0.1  # the router only forwards bytes
OBJECT_STORE_BYTES = 96 << 20  # Ray's shared-memory object store (requests are small)
MAX_REQUEST_BYTES = 32 << 20  # as `slamreloc serve --max-request-mb 32`
WATCH_S = 2.0  # seconds between a map replica's checks for its folder replaced on disk
READY_TIMEOUT_S = 120.0  # Serve's deployment + the first Health call through the proxy
MAP_NAME = re.compile(r"[A-Za-z0-9_.:-]+")


def _refuse(context: RayServegRPCContext, err: ServiceError) -> None:
    """Answer a unary call with the error: status code, details, `slamreloc-error` metadata."""
    context.set_code(err.grpc_code)
    context.set_details(err.message)
    context.set_trailing_metadata([(ERROR_METADATA_KEY, err.kind_name)])


@serve.deployment(ray_actor_options={"num_cpus": REPLICA_CPUS}, max_ongoing_requests=4,
                  health_check_period_s=10.0)
class MapReplica:
    """One replica of one map: loads it once, answers `localize` with protobuf bytes.
    `bounds`: the input bounds (`InputLimits`' fields) it holds, as its driver had them
    (`slamreloc --limit`, the driver's SLAMRELOC_<NAME>), whatever this process's environment
    says; None (a Serve config file) reads them from this process's environment."""

    def __init__(self, name: str, path: str, watch_s: float = WATCH_S,
                 bounds: dict[str, int] | None = None):
        # torch and the map load only here (the router and Serve's proxy never import them)
        from slamreloc.io.limits import limits, use_limits
        from slamreloc.service.maps import MapRegistry

        # before the map is read: its JSON and arrays are read under these bounds too
        if bounds is not None:
            use_limits(InputLimits(**bounds))
        else:
            limits()  # a variable misspelt in this environment fails the replica, named
        self._registry = MapRegistry({name: Path(path)})
        self._name = name
        if watch_s > 0:
            self._registry.watch(watch_s)

    def localize(self, request: bytes) -> tuple[int, bytes]:
        """(0, LocalizeResponse bytes), or (ErrorKind, UTF-8 message) for a refused request."""
        from slamreloc.service.localize import localize

        try:
            msg = pb.LocalizeRequest.FromString(request)
            return 0, localize(self._registry.get(self._name), msg).SerializeToString()
        except ServiceError as err:
            return int(err.kind), err.message.encode()
        except Exception as err:  # an allocation that failed is TOO_LARGE
            from slamreloc.errors import OutOfMemory, is_out_of_memory

            if not (isinstance(err, OutOfMemory) or is_out_of_memory(err)):
                raise
            text = str(err) if isinstance(err, OutOfMemory) else f"out of memory: {err}"
            return int(pb.TOO_LARGE), ServiceError(pb.TOO_LARGE, text).message.encode()

    def info(self) -> bytes:
        """This replica's MapInfo (protobuf bytes)."""
        return self._registry.get(self._name).info().SerializeToString()

    def reload(self) -> tuple[int, bytes]:
        """Load the folder again now: (0, ReloadMapResponse bytes) or (ErrorKind, message)."""
        try:
            served, changed = self._registry.reload(self._name)
        except ServiceError as err:
            return int(err.kind), err.message.encode()
        return 0, pb.ReloadMapResponse(map=served.info(), changed=changed).SerializeToString()

    def __del__(self) -> None:
        registry = getattr(self, "_registry", None)
        if registry is not None:
            registry.close()


@serve.deployment(ray_actor_options={"num_cpus": ROUTER_CPUS}, max_ongoing_requests=64)
class Router:
    """The ingress: the Relocalizer's unary RPCs, each routed to its map's deployment."""

    def __init__(self, maps: dict[str, DeploymentHandle], token: str | None = None):
        self._maps = maps
        self._token = token
        self._started = time.time()
        self._requests = 0

    # ---- plumbing ------------------------------------------------------------------------
    def _admit(self, context: RayServegRPCContext) -> None:
        """Count the call; UNAUTHENTICATED without the token (when one is set)."""
        self._requests += 1
        if self._token is None:
            return
        if not bearer_matches([v for k, v in context.invocation_metadata()
                               if k == "authorization"], self._token):
            raise ServiceError(pb.UNAUTHENTICATED, "missing or wrong token")

    def _handle(self, name: str) -> DeploymentHandle:
        """The map's handle; "" names the only map (as `MapRegistry.get`)."""
        if not name and len(self._maps) == 1:
            return next(iter(self._maps.values()))
        if name not in self._maps:
            known = ", ".join(sorted(self._maps))
            raise ServiceError(pb.UNKNOWN_MAP, f"no map named {quoted(name)} (served: {known})"
                               if name else f"name a map (served: {known})")
        return self._maps[name]

    async def _call(self, context: RayServegRPCContext, empty, work):
        """Run `work()` (a coroutine function returning the response); a refusal or an
        unexpected error becomes the status and metadata, with `empty` as the body."""
        try:
            self._admit(context)
            return await work()
        except ServiceError as err:
            _refuse(context, err)
        except Exception as err:  # noqa: BLE001 - answer INTERNAL, log, keep serving
            print(f"slamreloc ray router: {type(err).__name__}: {err}\n"
                  f"{traceback.format_exc()}", file=sys.stderr, flush=True)
            _refuse(context, ServiceError(pb.INTERNAL, f"{type(err).__name__}: {err}"))
        return empty

    # ---- the RPCs (named as in relocalizer.proto) ----------------------------------------
    async def Localize(self, request: pb.LocalizeRequest,
                       grpc_context: RayServegRPCContext) -> pb.LocalizeResponse:
        async def work() -> pb.LocalizeResponse:
            handle = self._handle(request.map)
            kind, payload = await handle.localize.remote(request.SerializeToString())
            if kind:
                raise ServiceError(kind, payload.decode())
            return pb.LocalizeResponse.FromString(payload)

        return await self._call(grpc_context, pb.LocalizeResponse(), work)

    async def Health(self, request: pb.HealthRequest,
                     grpc_context: RayServegRPCContext) -> pb.HealthResponse:
        async def work() -> pb.HealthResponse:
            return pb.HealthResponse(serving=True, protocol=PROTOCOL, version=__version__,
                                     num_maps=len(self._maps), num_sessions=0,
                                     uptime_s=time.time() - self._started,
                                     num_requests=self._requests)

        return await self._call(grpc_context, pb.HealthResponse(), work)

    async def ListMaps(self, request: pb.ListMapsRequest,
                       grpc_context: RayServegRPCContext) -> pb.ListMapsResponse:
        async def work() -> pb.ListMapsResponse:
            infos = [await h.info.remote() for h in self._maps.values()]
            return pb.ListMapsResponse(maps=[pb.MapInfo.FromString(b) for b in infos])

        return await self._call(grpc_context, pb.ListMapsResponse(), work)

    async def ReloadMap(self, request: pb.ReloadMapRequest,
                        grpc_context: RayServegRPCContext) -> pb.ReloadMapResponse:
        """Reloads the replica that takes the call at once; the map's other replicas see a
        replaced folder within their watch interval (`WATCH_S`)."""
        async def work() -> pb.ReloadMapResponse:
            kind, payload = await self._handle(request.map).reload.remote()
            if kind:
                raise ServiceError(kind, payload.decode())
            return pb.ReloadMapResponse.FromString(payload)

        return await self._call(grpc_context, pb.ReloadMapResponse(), work)

    async def Session(self, request_stream, grpc_context: RayServegRPCContext):
        """Not on Ray (see the module's docstring): refused as the native server refuses a
        session it cannot open, one `SessionUpdate.error` then the status (here
        FAILED_PRECONDITION: this server cannot hold a session), with nothing logged: a
        refusal any client may ask for. (Serve applies a status set on the context only with
        a message, and logs a traceback for one raised.)"""
        try:
            self._admit(grpc_context)  # the token first, as for every call
            raise ServiceError(pb.FAILED_PRECONDITION, "sessions are not served on Ray Serve; "
                               "serve the map with the grpc engine (`engine` grpc) for "
                               "the Session stream")
        except ServiceError as err:
            _refuse(grpc_context, err)
            yield pb.SessionUpdate(error=pb.SessionError(kind=err.kind, message=err.message))


# ---- building and deploying ------------------------------------------------------------------
def check_maps(maps: dict[str, Path]) -> dict[str, Path]:
    """Absolute map folders by name; InputError for a name Serve cannot carry or a path that is
    not a folder. (The map itself is read by its replicas: a defect fails the deployment, and
    `deploy` reports the replica's error. `slamreloc.map.format` is not imported here: it
    imports torch, which the router and Serve's controller do without.)"""
    if not maps:
        raise InputError("no maps to serve")
    out = {}
    for name, path in maps.items():
        problem = map_name_problem(name)  # the rule of the gRPC engine, then Ray's own
        if problem:
            raise InputError(f"map name {quoted(name)} {problem}")
        if not MAP_NAME.fullmatch(name):
            raise InputError(f"map name {name!r}: letters, digits and _ . : - only on Ray Serve")
        if "\0" in str(path):
            raise InputError(f"map {quoted(name)}: its folder's path holds a NUL byte")
        path = resolved(path)  # a link loop stays as given: not a map folder
        if not path.is_dir():
            raise InputError(f"{path}: not a map folder")
        out[name] = path
    return out


def application(maps: dict[str, Path], replicas: int = 1, *, replica_cpus: float = REPLICA_CPUS,
                token: str | None = None, watch_s: float = WATCH_S,
                bounds: InputLimits | None = None) -> Application:
    """The Serve application: a `MapReplica` deployment per map (`replicas` each, `replica_cpus`
    Ray CPUs each) behind one `Router`. `bounds`: the input bounds every map replica holds
    (`deploy` gives its own `limits()`); None: each replica's environment's."""
    if not 1 <= replicas <= MAX_REPLICAS:
        raise InputError(f"`replicas` {replicas}: 1 to {MAX_REPLICAS}")
    if not MIN_REPLICA_CPUS <= replica_cpus <= 64:
        raise InputError(f"`replica_cpus` {replica_cpus}: {MIN_REPLICA_CPUS} to 64")
    if token is not None and token_problem(token):
        raise InputError(f"the token {token_problem(token)}")
    check_seconds(watch_s, "watch_s", **WATCH_RULE)
    handles = {
        name: MapReplica.options(name=f"map-{name}", num_replicas=replicas,
                                 ray_actor_options={"num_cpus": replica_cpus})
        .bind(name, str(path), watch_s, None if bounds is None else asdict(bounds))
        for name, path in check_maps(maps).items()}
    return Router.options(name="router").bind(handles, token)


def build_app(args: dict[str, Any]) -> Application:
    """Application builder for a Serve config file (`deploy/ray-serve.yaml`): `args` holds
    `maps` (name -> folder on every node), and optionally `replicas`, `replica_cpus`,
    `token_file` (a file holding the token), `watch_s`."""
    known = {"maps", "replicas", "replica_cpus", "token_file", "watch_s"}
    if not isinstance(args, dict):
        raise InputError(f"args: must be a mapping of {sorted(known)}, got {repr(args)[:40]}")
    unknown = set(args) - known
    if unknown or not isinstance(args.get("maps"), dict):
        raise InputError(f"args: `maps` (name: folder) is required; known: {sorted(known)}; "
                         f"unknown: {sorted(unknown)}")
    maps = args["maps"]
    bad = next((k for k in maps if not isinstance(k, str)), None)
    if bad is not None:
        raise InputError(f"args: `maps` names must be strings (a map's name), got "
                         f"{repr(bad)[:40]}")
    bad = next((k for k, v in maps.items() if not isinstance(v, str) or not v.strip()), None)
    if bad is not None:
        raise InputError(f"args: `maps`.{str(bad)[:40]} must be a map folder's path, got "
                         f"{repr(maps[bad])[:40]}")
    token = None
    if "token_file" in args:  # given: it must hold a token (empty is not "no token")
        path = args["token_file"]
        if not isinstance(path, str) or not path.strip() or "\0" in path:
            raise InputError(f"args: `token_file` must name a file, got {repr(path)[:40]}")
        token = read_token(Path(path), environment=False)
    return application({str(k): Path(v) for k, v in maps.items()},
                       _config_number(args, "replicas", 1, whole=True),
                       replica_cpus=_config_number(args, "replica_cpus", REPLICA_CPUS),
                       token=token, watch_s=_config_number(args, "watch_s", WATCH_S))


def _config_number(args: dict[str, Any], key: str, default, whole: bool = False):
    """`args[key]` (else `default`): a JSON/YAML number, whole where `whole` (2.9 is not 2
    replicas, true is not 1); InputError naming the field otherwise."""
    value = args.get(key, default)
    kinds = (int,) if whole else (int, float)
    if isinstance(value, bool) or not isinstance(value, kinds) or value != value:
        what = "a whole number" if whole else "a number"
        raise InputError(f"args: `{key}` must be {what}, got {repr(value)[:40]}")
    return value
