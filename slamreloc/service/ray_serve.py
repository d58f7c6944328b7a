"""`slamreloc serve --engine ray`: start (or join) Ray, deploy the application of
`slamreloc.service.ray_app` (a router and a deployment per map), wait until it answers through
Serve's gRPC proxy, and stop it again. docs/serve.md, "Ray Serve", says what is and is not
supported there.
"""

from __future__ import annotations

import os
import socket
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import grpc
from ray import serve

from slamreloc.errors import InputError
from slamreloc.io.address import port_problem
from slamreloc.proto import relocalizer_pb2 as pb
from slamreloc.service.ray_app import (
    APP_NAME,
    MAX_REQUEST_BYTES,
    OBJECT_STORE_BYTES,
    READY_TIMEOUT_S,
    REPLICA_CPUS,
    ROUTE_PREFIX,
    ROUTER_CPUS,
    SERVICER_FUNCTION,
    WATCH_S,
    application,
)

if TYPE_CHECKING:
    from ray.serve.handle import DeploymentHandle


@dataclass
class Deployment:
    """What `deploy` started: where clients connect and how long it took."""

    host: str
    grpc_port: int
    maps: list[str]
    replicas: int
    app_name: str = APP_NAME
    started_ray: bool = False  # this process started the Ray instance (shutdown stops it)
    ray_start_s: float = 0.0  # seconds: ray.init + serve.start
    deploy_s: float = 0.0  # seconds: serve.run until the first Health answer through gRPC
    handle: DeploymentHandle | None = field(default=None, repr=False)

    @property
    def address(self) -> str:
        return f"{self.host}:{self.grpc_port}"


_current: Deployment | None = None


PROXY_READY_CHECK_S = 20.0  # each of Serve's 3 readiness checks of a starting proxy


def _port_free(port: int) -> bool:
    with socket.socket(socket.AF_INET6 if socket.has_ipv6 else socket.AF_INET) as s:
        try:
            s.bind(("::" if socket.has_ipv6 else "", port))
        except OSError:
            return False
    return True


def free_port() -> int:
    """A TCP port free right now (for port 0: Serve needs a number up front)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _wait_ready(port: int, timeout_s: float, metadata: list[tuple[str, str]]) -> None:
    """Until the application is RUNNING and a Health call through Serve's gRPC proxy answers;
    InputError when it failed (a map replica that cannot load) or `timeout_s` passed."""
    from slamreloc.proto.relocalizer_pb2_grpc import RelocalizerStub

    deadline = time.monotonic() + timeout_s
    while True:
        app = serve.status().applications.get(APP_NAME)
        state = "NOT_STARTED" if app is None else str(app.status.value)
        if state == "RUNNING":
            break
        if state in ("DEPLOY_FAILED", "UNHEALTHY"):
            why = "; ".join(f"{name}: {d.message}" for name, d in app.deployments.items()
                            if d.message)
            raise InputError(f"Ray Serve could not deploy the maps ({state}): "
                             f"{why or app.message}")
        if time.monotonic() > deadline:
            raise InputError(f"Ray Serve did not deploy the maps within {timeout_s:g} s "
                             f"({state}: {'' if app is None else app.message})")
        time.sleep(0.2)
    with grpc.insecure_channel(f"127.0.0.1:{port}") as channel:
        stub = RelocalizerStub(channel)
        while True:  # the proxy learns the routes a moment after the application runs
            try:
                stub.Health(pb.HealthRequest(), timeout=5.0, metadata=metadata)
                return
            except grpc.RpcError as err:
                if time.monotonic() > deadline:
                    raise InputError(f"Ray Serve's gRPC proxy on port {port} did not answer "
                                     f"within {timeout_s:g} s: {err.code()} {err.details()}") \
                        from None
                time.sleep(0.2)


def _check_cpus(need: float) -> None:
    """InputError when the Ray cluster has fewer CPUs than the replicas reserve (Serve would
    wait for them forever)."""
    import ray

    have = float(ray.cluster_resources().get("CPU", 0.0))
    if need > have + 1e-9:
        raise InputError(f"the replicas reserve {need:g} Ray CPUs, the Ray cluster has {have:g}: "
                         "fewer replicas, a smaller replica_cpus, or more CPUs")


def deploy(maps: dict[str, Path], replicas: int = 1, host: str = "127.0.0.1",
           grpc_port: int = 9000, *, http_port: int | None = None, address: str | None = None,
           num_cpus: int | None = None, replica_cpus: float = REPLICA_CPUS,
           token: str | None = None, watch_s: float = WATCH_S,
           object_store_bytes: int = OBJECT_STORE_BYTES,
           max_request_bytes: int = MAX_REQUEST_BYTES, log_to_driver: bool = True,
           timeout_s: float = READY_TIMEOUT_S) -> Deployment:
    """Serve `maps` (name -> folder) on Ray Serve; returns once a Health call through gRPC
    answers. `address`: a running Ray cluster ("auto" after `ray start --head`); None starts a
    local Ray instance with `num_cpus` CPUs (default: this machine's), no dashboard and a small
    object store. `host`/`http_port`: Serve's HTTP proxy (unused by this service but always
    started; None: a free port, so that another program's 8000 never stops the service); the
    gRPC proxy listens on all interfaces at `grpc_port`. Every map replica holds
    this process's input bounds (`slamreloc.io.limits.limits()`: `slamreloc --limit`, this
    environment's SLAMRELOC_<NAME>, `set_limits`), whatever the replica's environment says."""
    import ray

    from slamreloc.io.limits import limits

    global _current
    if _current is not None:
        raise InputError("already deployed in this process: shutdown() first")
    app = application(maps, replicas, replica_cpus=replica_cpus, token=token, watch_s=watch_s,
                      bounds=limits())
    http_port = free_port() if http_port is None else http_port
    for option, port in (("`port`", grpc_port), ("`http_port`", http_port)):
        if (problem := port_problem(port, option, any_free=False)) is not None:
            raise problem
    if not (1 << 16) <= max_request_bytes <= (2 << 30) - 1:
        raise InputError("max_request_bytes: 64 KiB to 2 GiB - 1")
    if address is None:
        for option, port in (("`port`", grpc_port),
                             ("`http_port` (Ray Serve's HTTP proxy, unused here)", http_port)):
            if not _port_free(port):
                raise InputError(f"{option} {port}: cannot listen there: the port is in use")
    t0 = time.perf_counter()
    started_ray = False
    if not ray.is_initialized():
        # read by Serve's proxy when it starts (workers inherit a local instance's
        # environment): `max_request_bytes` holds, whatever the environment said
        os.environ["RAY_SERVE_GRPC_MAX_MESSAGE_SIZE"] = str(max_request_bytes)
        os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
        # Serve kills a proxy that is not ready after 3 checks of 5 s: 15 s, less than the
        # start it waits for (60 s), and less than a proxy takes to import on a busy 2-core
        # machine (it was killed so, and `serve.start` failed). 3 x 20 s: that whole minute
        os.environ.setdefault("RAY_SERVE_PROXY_READY_CHECK_TIMEOUT_S", str(PROXY_READY_CHECK_S))
        with _own_sigterm():
            if address is None:
                ray.init(num_cpus=num_cpus or os.cpu_count() or 1, include_dashboard=False,
                         object_store_memory=object_store_bytes, log_to_driver=log_to_driver,
                         configure_logging=False)
            else:
                ray.init(address=address, log_to_driver=log_to_driver, configure_logging=False)
        started_ray = True
    try:
        serve.start(http_options={"host": host, "port": http_port},
                    grpc_options={"port": grpc_port,
                                  "grpc_servicer_functions": [SERVICER_FUNCTION]})
        _check_cpus(len(maps) * replicas * replica_cpus + ROUTER_CPUS)
        t1 = time.perf_counter()
        (handle,) = serve.run_many(
            [serve.RunTarget(app, name=APP_NAME, route_prefix=ROUTE_PREFIX)],
            wait_for_ingress_deployment_creation=False, wait_for_applications_running=False)
        _wait_ready(grpc_port, timeout_s,
                    [("authorization", f"Bearer {token}")] if token else [])
    except BaseException:
        _stop(started_ray)
        raise
    _current = Deployment(host, grpc_port, list(maps), replicas, APP_NAME, started_ray,
                          t1 - t0, time.perf_counter() - t1, handle)
    return _current


@contextmanager
def _own_sigterm() -> Iterator[None]:
    """The process's SIGTERM handler as it was before the block: `ray.init` installs Ray's
    native one, which aborts the process with a stack dump (exit -6, Ray's agents left
    running), where `slamreloc serve` stops Serve and Ray as on Ctrl-C."""
    import signal
    import threading

    main = threading.current_thread() is threading.main_thread()
    handler = signal.getsignal(signal.SIGTERM) if main else None
    try:
        yield
    finally:
        if main and handler is not None:
            signal.signal(signal.SIGTERM, handler)


def _stop(stop_ray: bool) -> None:
    import ray

    if ray.is_initialized():
        serve.shutdown()
        if stop_ray:
            ray.shutdown()


def shutdown() -> None:
    """Delete what `deploy` started: the Serve application and proxies, and the Ray instance
    (or the connection to a cluster) when `deploy` made it. Nothing when nothing is deployed."""
    global _current
    current, _current = _current, None
    if current is not None:
        _stop(current.started_ray)


def _interrupt(*_) -> None:
    raise KeyboardInterrupt


def _block() -> None:
    """Until Ctrl-C or SIGTERM (KeyboardInterrupt)."""
    while True:
        time.sleep(1.0)


def serve_forever(maps: dict[str, Path], replicas: int = 1, host: str = "127.0.0.1",
                  port: int = 9000, token: str | None = None, watch_s: float = WATCH_S,
                  max_request_bytes: int = MAX_REQUEST_BYTES) -> None:
    """`slamreloc serve --engine ray`: deploy, say where, block until Ctrl-C (or SIGTERM), then
    shut Serve and Ray down. Port 0: a free port (the printed one). `watch_s`: seconds between
    checks for a map folder replaced on disk (0: only ReloadMap); `max_request_bytes`: the
    largest request taken."""
    import signal

    if (problem := port_problem(port)) is not None:
        raise problem
    port = port or free_port()
    previous = signal.signal(signal.SIGTERM, _interrupt)
    try:
        if token is None:
            print(f"slamreloc serve: Ray Serve's gRPC proxy listens on every interface at "
                  f"port {port}, not only {host}; without a token anyone who reaches it can "
                  "use it", file=sys.stderr, flush=True)
        deploy(maps, replicas, host, port, token=token, watch_s=watch_s,
               max_request_bytes=max_request_bytes)
        try:
            print(f"listening on {host}:{port} (ray serve)", flush=True)
            _block()
        except KeyboardInterrupt:
            print("slamreloc serve: stopping (ray serve)", file=sys.stderr, flush=True)
        finally:
            shutdown()
    finally:
        signal.signal(signal.SIGTERM, previous)  # the caller's, as it was
