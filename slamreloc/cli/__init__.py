"""The `slamreloc` command line (typer + rich): the commands are in `slamreloc.cli.commands`,
each importing its pipeline only when it runs. Bad input: one line on stderr, exit status 2."""

from __future__ import annotations

import contextlib
import os
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from typing import NoReturn

from slamreloc.cli.commands import _flags, app, with_flags
from slamreloc.errors import Interrupted, SlamrelocError, is_out_of_memory, terminal_line
from slamreloc.runtime.progress import stop_bars

__all__ = ["_flags", "app", "main", "run", "with_flags"]

INTERRUPTED = 130  # the exit status of a command cut short by Ctrl-C or SIGTERM


@contextmanager
def sigterm_as_ctrl_c() -> Iterator[None]:
    """While the block runs, SIGTERM (`kill`, `timeout`, a service manager) ends a command as
    Ctrl-C does: one `interrupted` line, exit status 130, its cleanup run (a training
    checkpoint saved, temporary files removed). pycolmap's logging library installs, when
    imported, a handler that prints a native stack trace for SIGTERM: it is imported first, so
    ours replaces it; the handler found before is restored after (a command that serves until
    stopped installs its own inside)."""
    import signal
    import threading

    import pycolmap  # noqa: F401 - for its signal handler, replaced here

    def interrupt(signum, frame) -> None:
        raise KeyboardInterrupt

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGTERM, interrupt)
    try:
        yield
    finally:
        if _PROGRAM["program"]:  # the command is over, only its last line and exit are left:
            signal.signal(signal.SIGINT, signal.SIG_IGN)  # a signal now would end it with no
            signal.signal(signal.SIGTERM, signal.SIG_IGN)  # line, or a traceback (`run`)
        else:
            signal.signal(signal.SIGTERM, previous)


_PROGRAM = {"program": False}  # True in the `slamreloc` program (`run`), not in a test's `main`


def _command_line_problem(args: list[str]) -> str | None:
    """What click would take silently from a command line, or None: an option taking one value
    (or a flag and its `--no-` form) given more than once (click keeps the last, so `--port
    70000 --port 18080` would serve on a port nobody asked for twice), an empty value ('' is
    the path '.'), a number that breaks the number rule."""
    import typer.main

    group = typer.main.get_command(app)  # typer's own click: parameters read by duck typing
    command, params = group, list(group.params)
    for arg in args:
        if arg == "--":
            break
        if command is group and arg in getattr(group, "commands", {}):
            command = group.commands[arg]
            params = list(command.params)
    seen: dict[int, str] = {}
    for i, arg in enumerate(args):
        if arg == "--":
            break
        name, eq, value = arg.partition("=")
        for param in params:
            if (getattr(param, "param_type_name", "") != "option"
                    or name not in (*param.opts, *param.secondary_opts)):
                continue
            values = [value] if eq else args[i + 1:i + 1 + max(0, getattr(param, "nargs", 1))]
            if getattr(param, "is_flag", False):
                values = []
            for text, kind in zip(values, _value_kinds(param, len(values))):
                if not text.strip():  # '' would become the path '.' or an empty name
                    return f"{name} is given an empty value: give a value"
                problem = _number_text_problem(text, kind)
                if problem:
                    return f"{name}: {text!r} is {problem}"
            if getattr(param, "multiple", False) or getattr(param, "count", False):
                continue
            first = seen.get(id(param))
            if first == name:
                return f"{name} is given twice: give it once"
            if first is not None:
                return f"{first} and {name} set one option: give it once"
            seen[id(param)] = name
    return None


def _value_kinds(param, n: int) -> list[str]:
    """"integer", "float" or "" for each of an option's `n` values, from its annotation (typer
    keeps it as `type_descriptor`) or click's type name."""
    import types
    import typing

    annotation = getattr(getattr(param, "type_descriptor", None), "annotation", None)
    if annotation is None:
        return [getattr(getattr(param, "type", None), "name", "")] * n
    args = [a for a in typing.get_args(annotation) if a is not type(None)]
    if typing.get_origin(annotation) in (typing.Union, types.UnionType) and len(args) == 1:
        annotation, args = args[0], list(typing.get_args(args[0]))
    kinds = args if typing.get_origin(annotation) is tuple else [annotation] * n
    names = {int: "integer", float: "float"}
    return [names.get(k, "") for k in kinds]


def _number_text_problem(text: str, kind: str) -> str | None:
    """Why a number option's value breaks the project's number rule (`slamreloc.io.numbers`),
    in the words every other refusal by that rule uses: a whole-number option takes plain
    ASCII digits (not `1e3`, `1_0`, `0x10` or other scripts' digits), a number option plain
    ASCII decimals. nan / inf in a number option are left to its own check, which names its
    range. None where the value keeps the rule."""
    from slamreloc.io.numbers import DECIMAL_WORDS, WHOLE_WORDS, number_problem

    integer = "integer" in kind
    if not integer and "float" not in kind:
        return None
    if not integer and text.lower().lstrip("+-") in ("nan", "inf", "infinity"):
        return None
    problem = number_problem(text, integer=integer)
    if problem is None:
        return None
    return f"{problem} ({WHOLE_WORDS if integer else DECIMAL_WORDS})"


def _run_app() -> int | None:
    """Run the typer app; a command line it cannot parse (an unknown option, a missing or
    malformed value) is one `error:` line naming the option and exit status 2, as bad input
    is (not typer's framed panel); a bare `slamreloc` still shows the help. Returns an exit
    status the command asked for (`typer.Exit`), else None."""
    import typer

    try:
        from typer._click.exceptions import NoArgsIsHelpError
    except ImportError:  # typer before it vendored click
        from click.exceptions import NoArgsIsHelpError

    problem = _command_line_problem(sys.argv[1:])
    if problem:
        print(f"error: {terminal_line(problem)}", file=sys.stderr)
        return 2
    try:
        return app(standalone_mode=False)
    except NoArgsIsHelpError as err:  # as typer shows it
        from typer import rich_utils

        rich_utils.rich_format_error(err)
        return err.exit_code
    except typer.TyperException as err:
        if not hasattr(err, "format_message"):
            raise
        where = getattr(getattr(err, "ctx", None), "command_path", None) or "slamreloc"
        message = err.format_message().strip().rstrip(".")  # a value as given (no folding)
        print(f"error: {terminal_line(message)} (see {where} --help)", file=sys.stderr)
        return 2
    except typer.Abort as err:  # how typer on plain click answers a Ctrl-C
        if _after_interrupt(err):
            return INTERRUPTED
        print("error: aborted", file=sys.stderr)
        return 1


def _after_interrupt(err: BaseException) -> bool:
    """Whether `err` was raised while a Ctrl-C (or SIGTERM, `sigterm_as_ctrl_c`) was being
    handled, or because of one: the interruption is what the user should hear of."""
    seen = set()
    while err is not None and id(err) not in seen:
        if isinstance(err, KeyboardInterrupt):
            return True
        seen.add(id(err))
        err = err.__cause__ or err.__context__
    return False


def _end_interrupted(message: str = "interrupted") -> NoReturn:
    """One `interrupted` line, then exit status 130 at once: the command's own cleanup has
    run (its `finally` blocks and context managers while the interruption unwound), and so do
    the atexit handlers here; the interpreter's shutdown does not. That shutdown would not
    keep the status: a library cut short mid-import (open3d's native module) ends it with
    status 1, and CPython 3.11 ends a `python -m` run by SIGINT (status -2) once a
    KeyboardInterrupt has passed through exec() of a string (dataclasses, scipy's imports)."""
    import atexit
    import os

    print(terminal_line(message), file=sys.stderr)
    atexit._run_exitfuncs()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(INTERRUPTED)


# native libraries' own log lines (OpenCV's warnings, FFmpeg's through it) would come before
# the one `error:` line that says the same for the user; a user's own setting is kept
NATIVE_QUIET = {"OPENCV_LOG_LEVEL": "ERROR", "OPENCV_FFMPEG_LOGLEVEL": "-8"}


def _quiet_native_logs() -> None:
    """Silence OpenCV's and FFmpeg's log lines for this process (before cv2 is imported, as
    they read the environment once; through cv2 where it already is)."""
    import os

    for name, value in NATIVE_QUIET.items():
        os.environ.setdefault(name, value)
    cv2 = sys.modules.get("cv2")
    if cv2 is not None and os.environ["OPENCV_LOG_LEVEL"] == "ERROR":
        cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)


def _topics_unread() -> bool:
    """Whether `--topic` was given and the command loaded no bag with it."""
    rosbag = sys.modules.get("slamreloc.datasets.rosbag")
    return rosbag is not None and rosbag.default_topics_unread()


def main() -> None:
    import warnings

    _quiet_native_logs()
    for stream in (sys.stdout, sys.stderr):  # a terminal that cannot show every character
        with contextlib.suppress(AttributeError, ValueError):  # of a file name: escaped
            stream.reconfigure(errors="backslashreplace")

    warnings.formatwarning = (
        lambda message, *args, **kwargs: f"warning: {with_flags(str(message))}\n")
    try:
        try:
            with sigterm_as_ctrl_c():
                status = _run_app()
            if not status and _topics_unread():
                warnings.warn("`topic` was not used: this command read no ROS bag")
        finally:
            stop_bars()  # a bar left up by a failure: erased before the error line
        if status == INTERRUPTED:  # typer's answer to a Ctrl-C it caught, said nothing of
            _end_interrupted()
        if isinstance(status, int) and status:
            sys.exit(status)
    except Interrupted as err:
        _end_interrupted(f"interrupted: {with_flags(str(err).strip())}")
    except (SlamrelocError, ValueError, OSError) as err:
        # one line, whatever the message holds: a line break or a tab (in a library's
        # message, or a file's name) as its escape, never folded (`a  b.tum` is not `a b.tum`)
        message = with_flags(_error_text(err)) or type(err).__name__
        print(f"error: {terminal_line(message)}", file=sys.stderr)
        sys.exit(2)
    except Exception as err:  # an allocation that failed is one line too
        if _after_interrupt(err):  # e.g. a library's import cut short by Ctrl-C / SIGTERM
            _end_interrupted()
        if not is_out_of_memory(err):
            raise
        print(f"error: out of memory ({type(err).__name__}: {' '.join(str(err).split())[:200]})"
              if str(err) else "error: out of memory", file=sys.stderr)
        sys.exit(2)
    except KeyboardInterrupt:
        _end_interrupted()


def _error_text(err: Exception) -> str:
    """An error's message; an OSError that names its file as `PATH: reason` (`[Errno 28] No
    space left on device: 'out/x'` reads `out/x: No space left on device`), as every other
    error line names what it is about first."""
    if isinstance(err, OSError) and err.filename is not None and err.strerror:
        names = [err.filename] + ([err.filename2] if err.filename2 is not None else [])
        return f"{' -> '.join(os.fsdecode(n) for n in names)}: {err.strerror}"
    return str(err).strip()


def run() -> None:
    """The `slamreloc` program: `main`, with SIGTERM and SIGINT ignored from the command's end
    (`sigterm_as_ctrl_c`) while the process exits. Once the command has ended its outputs are
    complete; a signal landing then (its last line, or the interpreter's shutdown: seconds,
    with torch loaded) would end it by the signal with no line, or as interrupted: an exit
    status that says the outputs may not be whole. In a process that goes on after `main`
    (tests), call `main`."""
    import signal

    _PROGRAM["program"] = True
    try:
        main()
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        signal.signal(signal.SIGINT, signal.SIG_IGN)
