"""Errors that reach the user as one line: which file, what is wrong.

The library names a setting by its field in backticks (`min_parallax`, `port`); the command
line shows those that are its options as flags (`--min-parallax`, `--port`), so one message
reads right from Python and from the shell, and no module below the CLI names a flag.
"""


class SlamrelocError(Exception):
    """Base class; the CLI prints `error: <message>` and exits with status 2."""


class InputError(SlamrelocError):
    """Bad input: a missing or malformed file, wrong dimensions, a folder that is not a map."""


class OutOfMemory(InputError):
    """An input whose processing did not fit in the memory the process may use (the service
    answers it TOO_LARGE, as an input over a bound)."""


class Diverged(SlamrelocError):
    """Training whose loss stopped being a finite number; nothing of it is kept."""


class Interrupted(SlamrelocError):
    """Ctrl-C during long work; the message says what was saved and how to continue."""


def is_out_of_memory(err: BaseException) -> bool:
    """Whether `err` says an allocation failed (MemoryError, OpenCV's "Insufficient memory",
    torch's OutOfMemoryError, oneDNN's failed kernel creation: "could not create a primitive",
    its only report of a scratchpad it could not allocate, seen under an address-space cap)."""
    if isinstance(err, MemoryError) or type(err).__name__ == "OutOfMemoryError":
        return True
    text = str(err)
    return (type(err).__name__ == "error" and "Insufficient memory" in text
            or "can't allocate memory" in text
            or isinstance(err, RuntimeError) and text.strip() == "could not create a primitive"
            or "out of memory" in text.lower() and "alloc" in text.lower())


QUOTE_LIMIT = 80  # characters of given text a message repeats


def quoted(text, limit: int = QUOTE_LIMIT) -> str:
    """`text` (a map name, a host, a field a client sent) as an error message may echo it:
    repr-quoted and cut to about `limit` characters (a service's refusal travels in gRPC's
    trailing metadata, which has a size bound of its own)."""
    text = text if isinstance(text, str) else str(text)
    if len(text) <= limit:
        return repr(text)
    return f"{text[:limit]!r}... ({len(text)} characters)"


WORD_LIMIT = 300  # characters of one space-free run an error line shows


def escaped(text: str) -> str:
    """`text` with each character that is not printable (a line break, an ESC, a surrogate
    standing for a byte that is not UTF-8) written as its escape (\\n, \\x1b, \\udcfe): one
    line, writable as UTF-8."""
    return "".join(c if c.isprintable() else ascii(c)[1:-1] for c in text)


def terminal_line(text: str, limit: int = WORD_LIMIT) -> str:
    """`text` as one error line a terminal may show: characters that are not printable
    (an ESC sequence in a file name listed in a dataset, a line break) as their escapes, and
    any run without spaces over `limit` characters cut in its middle, so a 2 MB name makes a
    line that still ends with the problem."""
    def shown(word: str) -> str:
        word = escaped(word)
        if len(word) <= limit:
            return word
        half = limit // 2
        return f"{word[:half]}...({len(word)} characters)...{word[-half:]}"
    return " ".join(shown(w) for w in text.split(" "))
