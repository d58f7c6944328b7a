"""Network addresses an option names (`serve --host`, `view --host`): one rule for every
command that binds a port, checked before the server library tries (which would log, raise
or, viser, move on to the next port for ever)."""

from __future__ import annotations

import errno
import ipaddress
import socket

from slamreloc.errors import InputError, quoted

LOOPBACK_NAMES = ("localhost",)


def _bare(host: str) -> str:
    """`host` without the brackets of an IPv6 literal (`[::1]` -> `::1`)."""
    return host[1:-1] if host.startswith("[") and host.endswith("]") else host


def check_host(host: str) -> None:
    """InputError `` `host` 'H' PROBLEM `` unless `host` keeps `host_problem`'s rule."""
    problem = host_problem(host)
    if problem:
        raise InputError(f"`host` {quoted(host)} {problem}")


def host_problem(host: str) -> str | None:
    """Why `host` cannot be an address to bind (None when it can): empty, or not plain ASCII
    without blanks. The resolver would read other scripts' digits (full-width `１２７.0.0.1`)
    as ASCII ones and bind an address nobody typed, as the number rule refuses such digits in
    every number (`slamreloc.io.numbers`); a host name beyond ASCII is written in its
    IDNA form (`xn--...`)."""
    if not host:
        return "is empty: an address or a host name to bind"
    bad = next((c for c in host if not 0x21 <= ord(c) <= 0x7E), None)
    if bad is not None:
        return (f"holds {bad!a}: an address or host name is plain ASCII without blanks "
                "(127.0.0.1, ::1, a name; IDNA xn-- for other scripts)")
    bare = _bare(host)
    try:
        ipaddress.ip_address(bare)
    except ValueError:
        try:
            socket.inet_aton(bare)
        except OSError:
            return None  # a name
        # 127.1, 2130706433, 0177.0.0.1, 0x7f.1: the C resolver and gRPC read these forms
        # differently (0177 octal or decimal), so the address checked would not be the one bound
        return ("is a short, octal or hexadecimal IPv4 form, which libraries read "
                "differently: write four decimal numbers (127.0.0.1)")
    return None


GRPC_SCHEMES = ("dns", "unix", "unix-abstract", "ipv4", "ipv6", "vsock")  # gRPC's target names


def target_problem(target: str) -> str | None:
    """Why a client's `HOST:PORT` (an IPv6 host in brackets) cannot be connected to (None
    when it can): the host by `host_problem`'s rule, the port a decimal number from 1 to
    65535 (gRPC would wrap 65537 to 1). A gRPC target with a scheme (`dns:`, `unix:`,
    `ipv4:`...) is left to gRPC. clients/cpp applies the same rule to --server."""
    if not isinstance(target, str):
        return f"is {type(target).__name__}, not text (HOST:PORT)"
    if "://" in target or target.split(":", 1)[0] in GRPC_SCHEMES:
        return None
    host, sep, port = target.rpartition(":")
    if not sep or not host:
        return "is not HOST:PORT"
    problem = host_problem(host)
    if problem:
        return f"host {problem}"
    if not (port.isascii() and port.isdigit() and 1 <= int(port) <= 65535):
        return f"port {port!a} is not a number from 1 to 65535"
    return None


def is_loopback(host: str) -> bool:
    """Whether `host` names this machine only: localhost, 127.0.0.0/8, ::1, or IPv4-mapped
    ::ffff:127.0.0.1 (the short IPv4 forms are refused by `host_problem` first)."""
    if host in LOOPBACK_NAMES:
        return True
    bare = host.strip("[]")
    try:
        ip = ipaddress.ip_address(bare)
    except ValueError:
        return False
    mapped = getattr(ip, "ipv4_mapped", None)
    return ip.is_loopback or (mapped is not None and mapped.is_loopback)


def port_problem(port: int, option: str = "`port`", any_free: bool = True
                 ) -> InputError | None:
    """The one rule of a TCP port to listen on, for every server here: 1 to 65535, or 0 (any
    free port, where `any_free`). An InputError naming `option`, or None."""
    if (0 if any_free else 1) <= port <= 65535:
        return None
    free = "0 for any free one, or " if any_free else ""
    return InputError(f"{option} {port}: not a TCP port ({free}1 to 65535)")


def listen_address(host: str, port: int) -> str:
    """gRPC's `host:port`, an IPv6 literal in brackets ("[::1]:50051")."""
    bare = _bare(host)
    return f"[{bare}]:{port}" if ":" in bare else f"{bare}:{port}"


def bind_problem(host: str, port: int) -> InputError | None:
    """Why a server could not listen on host:port, found before its library tries: an
    InputError naming `host` (not resolvable, not an address of this machine) or `port` (in
    use, not allowed); None when a socket binds to one of its addresses."""
    bare = _bare(host)
    try:
        infos = socket.getaddrinfo(bare, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except (socket.gaierror, UnicodeError) as err:
        reason = getattr(err, "strerror", None) or str(err)
        return InputError(f"`host` {quoted(host)}: not an address, nor a name this machine "
                          f"resolves ({reason})")
    first: OSError | None = None
    for family, kind, proto, _, address in infos:
        try:
            with socket.socket(family, kind, proto) as probe:
                probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as gRPC does
                probe.bind(address)
                return None
        except OSError as err:
            first = first or err
    where = listen_address(host, port)
    code = first.errno if first is not None else None
    if code == errno.EADDRINUSE:
        return InputError(f"`port` {port}: cannot listen on {where}: the port is in use")
    if code == errno.EACCES:
        return InputError(f"`port` {port}: cannot listen on {where}: not allowed (a port below "
                          "1024 needs privileges)")
    if code == errno.EADDRNOTAVAIL:
        return InputError(f"`host` {quoted(host)}: cannot listen on {where}: not an address of "
                          "this machine")
    reason = first.strerror if first is not None else "no address"
    return InputError(f"`host` {quoted(host)} / `port` {port}: cannot listen on {where} "
                      f"({reason})")
