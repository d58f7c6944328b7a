"""Bounded file reads: a regular file of bounded size, opened without blocking on a pipe or
following what it must not; what is at a path, in words. (Writing outputs: `outputs`.)"""

from __future__ import annotations

import errno
import hashlib
import os
import re
import stat
import threading
from contextvars import ContextVar
from pathlib import Path
from typing import BinaryIO

from slamreloc.errors import InputError

# the event that cancels the long reads running in this context (a server stopping during a
# map load sets it): `sha256_of` checks it between its 1 MiB reads
CANCEL_READS: ContextVar[threading.Event | None] = ContextVar("slamreloc_cancel_reads",
                                                              default=None)


class ReadCancelled(Exception):
    """A read given up because CANCEL_READS's event was set."""


def open_regular(path: str | Path, what: str) -> BinaryIO:
    """`path` opened for reading, binary, if it is a regular file (a symbolic link to one is
    followed); InputError naming it otherwise. Every reader of a file the user or a client
    names goes through here: the file is opened without blocking (a named pipe with no writer
    would block `open` for ever, a device would be read for ever) and what was opened - not
    what the path named a moment earlier - is checked, so a file swapped for a pipe, a folder
    or a device between a check and the read is refused too."""
    path = Path(path)
    flags = (os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_NOCTTY", 0)
             | getattr(os, "O_CLOEXEC", 0) | getattr(os, "O_BINARY", 0))
    try:
        fd = os.open(path, flags)
    except FileNotFoundError:
        raise InputError(f"{path}: {what} file not found") from None
    except IsADirectoryError:  # not on Linux (a folder opens), but elsewhere
        raise InputError(f"{path}: {what} is not a regular file (a folder)") from None
    except OSError as err:
        raise InputError(f"{path}: cannot read {what} ({err.strerror or err})") from None
    try:
        mode = os.fstat(fd).st_mode
        if not stat.S_ISREG(mode):
            kind = ("a folder" if stat.S_ISDIR(mode) else "a named pipe" if stat.S_ISFIFO(mode)
                    else "a device" if stat.S_ISCHR(mode) or stat.S_ISBLK(mode)
                    else "a socket" if stat.S_ISSOCK(mode) else "not a file")
            raise InputError(f"{path}: {what} is not a regular file ({kind})")
        if getattr(os, "O_NONBLOCK", 0):
            os.set_blocking(fd, True)
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise


def regular_size(f: BinaryIO) -> int:
    """The size of a file opened by `open_regular` (from its descriptor, not its path)."""
    return os.fstat(f.fileno()).st_size


def read_bytes(path: str | Path, what: str, limit: int | str) -> bytes:
    """The bytes of a regular file of at most `limit` bytes (a number, or the name of a bound
    the user may raise: `slamreloc.io.limits`); InputError naming it otherwise (also for a
    pipe, a device or a folder: see `open_regular`)."""
    from slamreloc.io.limits import bytes_text, limits, over_limit

    path = Path(path)
    most = getattr(limits(), limit) if isinstance(limit, str) else limit

    noun = what if what.endswith("file") else f"{what} file"  # "frame names file" once

    def too_large(size: str) -> InputError:
        if isinstance(limit, str):
            return InputError(f"{path}: {noun} of " + over_limit(limit, size))
        return InputError(f"{path}: {noun} of {size}, over the {bytes_text(most)} a {noun} "
                          "may hold")

    with open_regular(path, what) as f:
        try:
            size = regular_size(f)
            if size > most:
                raise too_large(bytes_text(size))
            # as much as it holds (never a buffer of the bound's size: `--limit` may be
            # huge), then on in chunks to the bound: a file growing while read is bounded too
            data = f.read(min(most, size) + 1)
            while len(data) <= most:
                more = f.read(min(most + 1 - len(data), 1 << 20))
                if not more:
                    break
                data += more
        except OSError as err:
            raise InputError(f"{path}: cannot read {what} ({err.strerror or err})") from None
    if len(data) > most:
        raise too_large(f"more than {bytes_text(most)}")
    return data


def read_text(path: str | Path, what: str, limit: int | str) -> str:
    """`read_bytes` as UTF-8 text (a leading byte-order mark, which some editors write, is
    dropped: every text file is read the same way, JSON's too); InputError for bytes that are
    not UTF-8 or that hold a NUL byte (no text format has one; as a name it would be cut)."""
    return read_text_bytes(path, what, limit).decode("utf-8-sig")


def read_text_bytes(path: str | Path, what: str, limit: int | str) -> bytes:
    """The bytes of a text file by `read_text`'s rule (the bound, UTF-8, no NUL byte), not
    decoded: for a reader that walks a large file line by line, one copy of it in memory
    (its size in bytes) rather than a str of up to 4 bytes a character."""
    data = read_bytes(path, what, limit)
    bad = _utf8_error(data)
    if bad is not None:
        raise InputError(f"{path}: {what} is not UTF-8 text (byte {bad})")
    nul = data.find(b"\0")
    if nul >= 0:
        line = data.count(b"\n", 0, nul) + 1
        raise InputError(f"{path}:{line}: {what} holds a NUL byte (byte {nul}); text files "
                         "have none")
    return data


UTF8_CHUNK = 1 << 20  # bytes decoded at a time to check a text file's UTF-8


def _utf8_error(data: bytes) -> int | None:
    """The offset in bytes of the first byte of `data` that is not UTF-8 (None: it is all
    UTF-8), decoded UTF8_CHUNK bytes at a time, each chunk ending before a character's
    first byte (never inside one), so that no str of the whole file is made."""
    if data.isascii():
        return None
    start = 0
    while start < len(data):
        end = min(start + UTF8_CHUNK, len(data))
        for _ in range(3):  # back to a character's first byte (a UTF-8 character is <= 4)
            if end < len(data) and 0x80 <= data[end] < 0xC0:
                end -= 1
        try:
            data[start:end].decode("utf-8")
        except UnicodeDecodeError as err:
            return start + err.start
        start = end
    return None


# What a line of `plain_lines` may not hold: a carriage return not followed by a line feed, or
# a blank or line break other than a space, a tab and a line feed (\v, \f, \x1c-\x1f, U+0085,
# U+00A0, U+1680, U+2000-U+200A, U+2028, U+2029, U+202F, U+205F, U+3000: exactly what
# `str.isspace` takes besides those, so that `str.split()` of a line that passes splits at
# spaces and tabs only, and no line holds a break `str.splitlines` would see). clients/cpp's
# `plain_text_problem` holds the same list.
_NOT_PLAIN = re.compile(r"\r(?!\n)|[^\S \t\n\r]")
PLAIN_RULE = "fields are separated by spaces or tabs only, lines end at a line feed (or CR LF)"


def plain_lines(text: str, path: str | Path, what: str) -> list[tuple[int, str]]:
    """(line number from 1, line) of each line of `text` (a file read by `read_text`: UTF-8, a
    leading byte-order mark dropped, no NUL byte) by the plain line rule of slamreloc's
    line-and-field lists (TUM's rgb.txt, depth.txt and groundtruth.txt, TUM trajectories),
    which the C++ client follows too: lines end at "\\n" (a "\\r" before it is dropped), and a
    line's fields are separated by spaces and tabs only, so `line.split()` gives them. Any
    other blank or line break (\\v, \\f, a lone \\r, U+0085, NBSP, U+2003, U+2028, ...) is an
    InputError `FILE:LINE: WHAT holds ...` naming it: readers differ on whether it ends a line,
    separates fields or belongs to one (Python's `str.splitlines` and `str.split` take it for a
    break, C's and C++'s streams each for some of them). Other characters (other control
    characters included) belong to the field they are in."""
    bad = _NOT_PLAIN.search(text)
    if bad is not None:
        line = text.count("\n", 0, bad.start()) + 1
        code = ord(bad.group())
        kind = ("a carriage return not followed by a line feed" if code == 0x0D
                else "a blank or line break other than a space, a tab or a line feed")
        raise InputError(f"{path}:{line}: {what} holds {kind} (U+{code:04X}): {PLAIN_RULE}")
    lines = text.split("\n")
    if lines[-1] == "":  # the end of the last line, not a line
        lines.pop()
    return [(i, line[:-1] if line.endswith("\r") else line) for i, line in enumerate(lines, 1)]


def sha256_of(f: BinaryIO) -> str:
    """SHA-256 of an open file from its current position to its end; ReadCancelled as soon
    as this context's CANCEL_READS event is set (a 15 GiB file takes a minute)."""
    h = hashlib.sha256()
    cancelled = CANCEL_READS.get()
    for chunk in iter(lambda: f.read(1 << 20), b""):
        if cancelled is not None and cancelled.is_set():
            raise ReadCancelled(f"{getattr(f, 'name', 'a file')}: read cancelled")
        h.update(chunk)
    return h.hexdigest()


def optional_file(path: Path, what: str) -> bool:
    """Whether a dataset's optional file (intrinsics.txt, depth.txt, a split file) is there:
    False where nothing is at `path`, True for a file (or a link to one); InputError for
    anything else there (a folder, a named pipe, a device, a broken link), which is neither
    "absent" (a default would be taken silently) nor readable."""
    if not os.path.lexists(path):
        return False
    st = stat_or_none(path)
    if st is None:
        raise InputError(f"{path}: {what} is a broken link")
    if not stat.S_ISREG(st.st_mode):
        raise InputError(f"{path}: {what} is {file_kind(st.st_mode)}, not a file")
    return True


def file_kind(mode: int) -> str:
    """What a file mode is, in words ("a folder", "a named pipe", ...)."""
    return ("a folder" if stat.S_ISDIR(mode) else "a file" if stat.S_ISREG(mode)
            else "a named pipe" if stat.S_ISFIFO(mode)
            else "a device" if stat.S_ISCHR(mode) or stat.S_ISBLK(mode)
            else "a socket" if stat.S_ISSOCK(mode)
            # an lstat's mode: `stat_or_none` gives it where the link cannot be followed
            else "a symbolic link loop" if stat.S_ISLNK(mode) else "something else")


def is_link_loop(path: Path) -> bool:
    """Whether following the symbolic links at `path` goes round in a loop."""
    try:
        os.stat(path)
    except OSError as err:
        return err.errno == errno.ELOOP
    return False


def file_identity(path: str | Path, follow: bool = True) -> tuple[int, ...] | None:
    """Which file `path` names now: (device, inode), and for a regular file its size and
    modification time too (a file rewritten in place keeps its inode); None where nothing
    is there. Two equal identities: the same file, unchanged between the two looks."""
    try:
        st = os.stat(path, follow_symlinks=follow)
    except OSError:
        return None
    if stat.S_ISREG(st.st_mode):
        return st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns
    return st.st_dev, st.st_ino


def stat_or_none(path: Path) -> os.stat_result | None:
    """`os.stat` of `path` (symbolic links followed, the kernel's own links under /proc
    included: `/dev/stdout` is the pipe or terminal it stands for); None where nothing is,
    a dangling link included."""
    try:
        return os.stat(path)
    except (FileNotFoundError, NotADirectoryError):
        return None
    except OSError:  # a link loop, a name too long, no permission to look: not writable
        return os.lstat(path) if os.path.lexists(path) else None


def check_folder(path: Path, what: str) -> None:
    """InputError unless `path` is a folder (a symbolic link to one is followed): "WHAT folder
    not found", or what is there instead ("WHAT exists and is a named pipe, not a folder");
    nothing is opened or read."""
    st = stat_or_none(Path(path))
    if st is None:
        raise InputError(f"{path}: {what} folder not found")
    if not stat.S_ISDIR(st.st_mode):
        raise InputError(f"{path}: {what} exists and is {file_kind(st.st_mode)}, not a folder")


def resolved(path: str | Path) -> Path:
    """`path` with its links followed as far as they resolve (made absolute where they do
    not: a loop, a dangling link)."""
    try:
        return Path(path).resolve()
    except (OSError, RuntimeError):
        return Path(os.path.abspath(path))


def relation(a: Path, b: Path) -> str | None:
    """How the resolved path `a` stands to the resolved path `b`, in the words of a refusal:
    "is", "lies inside", "would hold" (b lies inside a), or None where they are apart."""
    if a == b:
        return "is"
    if a.is_relative_to(b):
        return "lies inside"
    if b.is_relative_to(a):
        return "would hold"
    return None


def relation_on_disk(a: Path, b: Path, ids_a: list | None = None,
                     ids_b: list | None = None) -> str | None:
    """`relation`, told by the names and by what they are on disk now (device and inode of
    each existing folder on the way), so a second name for the same folder (a bind mount, a
    hard link) is no way around it: an output aimed at an input. `ids_a`, `ids_b`: the
    paths' `disk_identities`, where the caller compares one path with many."""
    how = relation(a, b)
    if how is not None:
        return how
    ids_a = disk_identities(a) if ids_a is None else ids_a
    ids_b = disk_identities(b) if ids_b is None else ids_b
    if not ids_a or not ids_b:
        return None
    if ids_a[0][0] == 0 and ids_b[0][0] == 0 and ids_a[0][1] == ids_b[0][1]:
        return "is"
    if ids_b[0][0] == 0 and ids_b[0][1] in {i for _, i in ids_a}:
        return "lies inside"
    if ids_a[0][0] == 0 and ids_a[0][1] in {i for _, i in ids_b}:
        return "would hold"
    return None


def disk_identities(path: Path) -> list[tuple[int, tuple[int, int]]]:
    """(how many names up from `path`, (device, inode)) of `path` and of each of its existing
    parents, nearest first; [] where none can be read."""
    out = []
    for up, one in enumerate((path, *path.parents)):
        try:
            st = os.stat(one)
        except (OSError, ValueError):
            continue
        out.append((up, (st.st_dev, st.st_ino)))
    return out
