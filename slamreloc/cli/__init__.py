"""The `slamreloc` command line (typer + rich): the commands are in `slamreloc.cli.commands`,
each importing its pipeline only when it runs. Bad input: one line on stderr, exit status 2."""

from __future__ import annotations

import sys

from slamreloc.cli.commands import _flags, app, with_flags
from slamreloc.errors import Interrupted, SlamrelocError, is_out_of_memory
from slamreloc.runtime.progress import stop_bars

__all__ = ["_flags", "app", "main", "with_flags"]


def main() -> None:
    import warnings

    warnings.formatwarning = (
        lambda message, *args, **kwargs: f"warning: {with_flags(str(message))}\n")
    try:
        try:
            app()
        finally:
            stop_bars()  # a bar left up by a failure: erased before the error line
    except Interrupted as err:
        print(f"interrupted: {with_flags(' '.join(str(err).split()))}", file=sys.stderr)
        sys.exit(130)
    except (SlamrelocError, ValueError, OSError) as err:
        # one line, whatever the message holds (some libraries' messages span lines)
        message = with_flags(' '.join(str(err).split())) or type(err).__name__
        print(f"error: {message}", file=sys.stderr)
        sys.exit(2)
    except Exception as err:  # an allocation that failed is one line too
        if not is_out_of_memory(err):
            raise
        print(f"error: out of memory ({type(err).__name__}: {' '.join(str(err).split())[:200]})"
              if str(err) else "error: out of memory", file=sys.stderr)
        sys.exit(2)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        sys.exit(130)

