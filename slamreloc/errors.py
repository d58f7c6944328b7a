"""Errors that reach the user as one line: which file, what is wrong."""


class SlamrelocError(Exception):
    """Base class; the CLI prints `error: <message>` and exits with status 2."""


class InputError(SlamrelocError):
    """Bad input: a missing or malformed file, wrong dimensions, a folder that is not a map."""


class Interrupted(SlamrelocError):
    """Ctrl-C during long work; the message says what was saved and how to continue."""
