"""`slamreloc serve`: the relocalization service (gRPC; docs/serve.md)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from slamreloc.cli.choices import Engine
from slamreloc.errors import InputError
from slamreloc.service import MAX_REPLICAS, TOKEN_ENV

def map_names(maps: list[Path], names: list[str]) -> dict[str, Path]:
    """name -> folder: the `--name`s in order, then the folders' own names; each a name the
    wire takes (`map_name_problem`: printable, no spaces, bounded). The folders are checked
    where they are loaded; one whose name cannot be known (a symbolic link loop) is refused
    here, saying what is there (`map_folder_problem`)."""
    from slamreloc.map.format import map_folder_problem
    from slamreloc.proto.messages import map_name_problem, quoted

    if len(names) > len(maps):
        raise InputError(f"{len(names)} `name` for {len(maps)} maps")
    out: dict[str, Path] = {}
    for i, path in enumerate(maps):
        try:
            name = names[i] if i < len(names) else path.resolve().name
        except (OSError, RuntimeError):  # a symbolic link loop
            raise InputError(f"{path}: {map_folder_problem(path)}") from None
        problem = map_name_problem(name)
        if problem:
            raise InputError(f"{path}: map name {quoted(name, 40)} {problem} (`name`)")
        if name in out:
            raise InputError(f"{path}: two maps named {quoted(name, 40)} (`name`)")
        out[name] = path
    return out


def require_ray() -> None:
    """InputError unless Ray Serve can be imported (`--engine ray`)."""
    try:
        import ray  # noqa: F401
        from ray import serve  # noqa: F401
    except ImportError as err:
        raise InputError("Ray is not installed (pip install 'ray[serve]'), which `engine` ray "
                         f"needs ({' '.join(str(err).split())[:120]})") from None


def serve(
    maps: Annotated[Optional[list[Path]], typer.Argument(
        metavar="MAP", help="map folders to serve (none: only with --learned-maps)")]
    = None,
    name: Annotated[Optional[list[str]], typer.Option(
        help="a map's name, in the order of the maps (default: the folder's name)")] = None,
    host: Annotated[str, typer.Option(
        help="address to bind; a non-loopback one needs a token")] = "127.0.0.1",
    port: Annotated[int, typer.Option(help="port (0: any free one, printed)")] = 50051,
    workers: Annotated[Optional[int], typer.Option(
        help="localizations at once (the cores are split between them) [default: 1]")] = None,
    max_sessions: Annotated[Optional[int], typer.Option(
        help="SLAM sessions open at once [default: 8]")] = None,
    max_learning_sessions: Annotated[Optional[int], typer.Option(
        help="of those, sessions that learn their map (no map; about 2 GB each when full) "
             "[default: 2]")] = None,
    token_file: Annotated[Optional[Path], typer.Option(
        help=f"file holding the token every call must carry (or ${TOKEN_ENV})")] = None,
    tls_cert: Annotated[Optional[Path], typer.Option(help="TLS certificate (PEM)")] = None,
    tls_key: Annotated[Optional[Path], typer.Option(help="TLS private key (PEM)")] = None,
    max_request_mb: Annotated[float, typer.Option(help="largest request accepted")] = 32.0,
    max_held_mb: Annotated[Optional[float], typer.Option(
        help="requests held at once (received, queued, answered), in MiB; more are refused "
             "OVERLOADED at once (at least one request of --max-request-mb) [default: 256]")]
    = None,
    watch: Annotated[float, typer.Option(
        help="seconds between checks for a map folder replaced on disk (0: only ReloadMap)")]
    = 2.0,
    engine: Annotated[Engine, typer.Option(
        help="grpc: this process; ray: deployments on Ray Serve (one per map, --replicas)")]
    = Engine.grpc,
    replicas: Annotated[Optional[int], typer.Option(
        help="--engine ray: replicas per map [default: 1]")] = None,
    learned_maps: Annotated[Optional[Path], typer.Option(
        help="folder where learning sessions save their maps (SessionSave NAME: DIR/NAME, "
             "then served as NAME); without it a save is refused")] = None,
    max_learned_maps: Annotated[Optional[int], typer.Option(
        help="--learned-maps: most maps sessions may save under new names (each stays "
             "loaded; a save over one of them is always taken) [default: 64]")] = None,
) -> None:
    """Serve MAPs over gRPC (protocol slamreloc.v1): Localize, SLAM sessions, health, list and
    reload maps. Runs until Ctrl-C."""
    # the options in their own units (the service's config takes bytes and seconds); NaN fails
    if not 1 / 16 <= max_request_mb <= 2047:
        raise InputError(f"--max-request-mb {max_request_mb}: 0.0625 to 2047")
    if max_held_mb is not None and not 1 / 16 <= max_held_mb <= 65536:
        raise InputError(f"--max-held-mb {max_held_mb}: 0.0625 to 65536")
    from slamreloc.service.server import WATCH_RULE, check_seconds

    check_seconds(watch, "watch", **WATCH_RULE)
    if replicas is not None and not 1 <= replicas <= MAX_REPLICAS:
        raise InputError(f"`replicas` {replicas}: 1 to {MAX_REPLICAS}")
    maps = list(maps or [])
    if not maps and learned_maps is None:
        raise InputError("no MAP to serve: give map folders, or --learned-maps DIR for a server "
                         "whose sessions learn their maps")
    if max_learned_maps is not None and learned_maps is None:
        raise InputError("--max-learned-maps bounds the maps saved into --learned-maps; give "
                         "that folder, or leave it out")
    named = map_names(maps, list(name or []))
    from slamreloc.service.maps import check_served_folders

    check_served_folders(named)  # before any map is read, whichever engine reads them
    from slamreloc.service.server import read_token

    token = read_token(token_file)
    if engine == Engine.ray:
        require_ray()
        from slamreloc.service.ray_serve import serve_forever as ray_serve_forever

        if tls_cert is not None or tls_key is not None:
            raise InputError("--engine ray: Ray Serve's gRPC proxy has no TLS; use --engine grpc "
                             "or a TLS-terminating proxy in front (docs/serve.md)")
        if learned_maps is not None:
            raise InputError("--engine ray: learning sessions (--learned-maps) are served by "
                             "--engine grpc only")
        grpc_only = [f"--{o}" for o, v in (("workers", workers), ("max-sessions", max_sessions),
                     ("max-learning-sessions", max_learning_sessions),
                     ("max-held-mb", max_held_mb)) if v is not None]
        if grpc_only:
            raise InputError(f"--engine ray: {', '.join(grpc_only)} applies to --engine grpc "
                             "only (Ray Serve scales a map by --replicas and serves no "
                             "sessions)")
        if token is None:
            raise InputError("--engine ray: Ray Serve's gRPC proxy listens on every interface, "
                             f"whatever --host says; give a token (--token-file or ${TOKEN_ENV})")
        ray_serve_forever(named, replicas=replicas or 1, host=host, port=port, token=token,
                          watch_s=watch, max_request_bytes=int(max_request_mb * (1 << 20)))
        return
    if replicas is not None:
        raise InputError("--replicas applies to --engine ray only (--engine grpc serves each "
                         "map from this process; --workers sets its localizations at once)")
    from slamreloc.service.server import ServeConfig, serve_forever

    serve_forever(named, ServeConfig(
        host=host, port=port, workers=ServeConfig.workers if workers is None else workers,
        max_sessions=ServeConfig.max_sessions if max_sessions is None else max_sessions,
        max_learning_sessions=(ServeConfig.max_learning_sessions
                               if max_learning_sessions is None else max_learning_sessions),
        token=token,
        tls_cert=tls_cert, tls_key=tls_key, max_request_bytes=int(max_request_mb * (1 << 20)),
        max_held_bytes=(ServeConfig.max_held_bytes if max_held_mb is None
                        else int(max_held_mb * (1 << 20))),
        watch_s=watch, learned_maps=learned_maps,
        max_learned_maps=(ServeConfig.max_learned_maps if max_learned_maps is None
                          else max_learned_maps)))
