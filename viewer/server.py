"""The viser server: bound to 127.0.0.1 by default, no share button, served until Ctrl-C."""

from __future__ import annotations

import contextlib
import io
import signal
import threading
from collections.abc import Callable

from slamreloc.errors import InputError
from slamreloc.viewer.data import SceneData, ViewerInputs
from slamreloc.viewer.loaders import load_scene_data
from slamreloc.viewer.scene import SceneHandles, build_scene

TITLE = "slamreloc viewer"


def make_server(host: str = "127.0.0.1", port: int = 8080):
    """A ViserServer on host:port (viser moves to the next free port when it is busy: read the
    real one with `server.get_port()`), with the share-URL button hidden."""
    import viser

    with contextlib.redirect_stdout(io.StringIO()):  # viser's own banner; we print the address
        server = viser.ViserServer(host=host, port=port, label=TITLE, verbose=False)
    server.gui.configure_theme(
        show_share_button=False, control_width="medium",
        dark_mode=False, show_logo=False)
    if hasattr(server.gui, "set_panel_label"):
        server.gui.set_panel_label(TITLE)
    return server


def address(server, host: str) -> str:
    shown = "127.0.0.1" if host in ("127.0.0.1", "localhost") else host
    return f"http://{shown}:{server.get_port()}"


def check_address(host: str, port: int) -> None:
    """InputError unless `host` is an address of this machine (or a name resolving to one;
    `slamreloc.io.address`, the rule `serve` keeps) and `port` is a TCP port, 0 to 65535 (0:
    any free one, as `serve --port 0`), before anything is read. A port in use is viser's to
    handle (it moves to the next one); an address that is not this machine's would have it
    try port after port for ever."""
    from slamreloc.io.address import bind_problem, check_host, port_problem

    check_host(host)
    _viser_binds(host)
    if (problem := port_problem(port)) is not None:  # serve's rule: 0 takes any free port
        raise problem
    refusal = bind_problem(host, 0)
    if refusal is not None:
        raise refusal


def first_free_port(host: str, port: int) -> int:
    """`port`, or the first port above it that `host` can bind where it is busy (what viser
    would move to; past 65535 viser's own search fails in its thread and the viewer never
    starts); 0 stays 0 (any free port). InputError where none is free up to 65535."""
    import socket

    if port == 0:
        return 0
    family = socket.getaddrinfo(host, None, type=socket.SOCK_STREAM)[0][0]
    for candidate in range(port, 65536):
        with socket.socket(family, socket.SOCK_STREAM) as probe:
            # as a server binds: a port whose last connection waits out TIME_WAIT is free
            probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                probe.bind((host, candidate))
            except OSError:
                continue
        return candidate
    raise InputError(f"`port` {port}: in use, and so is every port above it up to 65535: give "
                     "another (0: any free one)")


def _viser_binds(host: str) -> None:
    """InputError for an address the address rule takes but viser's server cannot bind (it
    would hang, or fail after the map is read): an IPv6 address in brackets, an IPv4 address
    written as IPv6 (::ffff:a.b.c.d)."""
    import ipaddress

    if host.startswith("["):
        raise InputError(f"`host` {host}: write an IPv6 address without brackets (::1)")
    try:
        ip = ipaddress.ip_address(host)
    except ValueError:
        return
    if ip.version == 6 and ip.ipv4_mapped is not None:
        raise InputError(f"`host` {host}: an IPv4 address written as IPv6, which the viewer "
                         f"cannot bind; give {ip.ipv4_mapped}")


def start(inputs: ViewerInputs, data: SceneData | None = None) -> tuple[object, SceneHandles]:
    """Read the inputs (InputError before any port is bound), start the server, build the
    scene. Returns (server, handles); stop with `handles.stop(); server.stop()`."""
    check_address(inputs.host, inputs.port)
    data = data if data is not None else load_scene_data(inputs)
    server = make_server(inputs.host, first_free_port(inputs.host, inputs.port))
    if not server.get_port():  # a viser that reports the 0 it was given, not the port it took
        server.stop()
        raise InputError("`port` 0: this viser cannot say which port it took; give a port")
    try:
        handles = build_scene(server, data)
    except BaseException:
        server.stop()
        raise
    return server, handles


def serve(inputs: ViewerInputs, data: SceneData | None = None,
          echo: Callable[[str], None] = print, stop: threading.Event | None = None) -> None:
    """Serve the viewer until Ctrl-C (or SIGTERM, or `stop` set); prints the address."""
    server, handles = start(inputs, data)
    stop = stop or threading.Event()
    port = server.get_port()
    moved = f" (port {inputs.port} was busy)" if inputs.port and port != inputs.port else ""
    echo(f"viewer: {address(server, inputs.host)}{moved}  - press Ctrl-C to stop")
    old = None
    if threading.current_thread() is threading.main_thread():
        old = signal.signal(signal.SIGTERM, lambda *_: stop.set())
    try:
        while not stop.wait(0.5):
            pass
    except KeyboardInterrupt:
        pass
    finally:
        if old is not None:
            signal.signal(signal.SIGTERM, old)
        handles.stop()
        with contextlib.redirect_stdout(io.StringIO()):
            server.stop()
        echo("viewer stopped")
