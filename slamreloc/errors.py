"""Errors that reach the user as one line: which file, what is wrong.

The library names a setting by its field in backticks (`min_parallax`, `port`); the command
line shows those that are its options as flags (`--min-parallax`, `--port`), so one message
reads right from Python and from the shell, and no module below the CLI names a flag.
"""


class SlamrelocError(Exception):
    """Base class; the CLI prints `error: <message>` and exits with status 2."""


class InputError(SlamrelocError):
    """Bad input: a missing or malformed file, wrong dimensions, a folder that is not a map."""


class Interrupted(SlamrelocError):
    """Ctrl-C during long work; the message says what was saved and how to continue."""
