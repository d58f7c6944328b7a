"""The `slamreloc` command line (typer + rich): the commands are in `slamreloc.cli.commands`,
each importing its pipeline only when it runs. Bad input: one line on stderr, exit status 2."""

from __future__ import annotations

import sys

from slamreloc.cli.commands import _flags, app, with_flags
from slamreloc.errors import Interrupted, SlamrelocError

__all__ = ["_flags", "app", "main", "with_flags"]


def main() -> None:
    import warnings

    warnings.formatwarning = (
        lambda message, *args, **kwargs: f"warning: {with_flags(str(message))}\n")
    try:
        app()
    except Interrupted as err:
        print(f"interrupted: {with_flags(' '.join(str(err).split()))}", file=sys.stderr)
        sys.exit(130)
    except (SlamrelocError, ValueError, OSError) as err:
        # one line, whatever the message holds (some libraries' messages span lines)
        message = with_flags(' '.join(str(err).split())) or type(err).__name__
        print(f"error: {message}", file=sys.stderr)
        sys.exit(2)
    except MemoryError:
        print("error: out of memory", file=sys.stderr)
        sys.exit(2)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        sys.exit(130)

