"""The write lock of a folder output (a map, an sfm dataset, an exported COLMAP model, a
rendered synthetic scene), and the clean-up of what a killed writer left beside it.

A writer holds an exclusive lock on `.NAME.lock` beside the folder (removed when it is done);
a second writer fails at once (InputError naming it). Under that lock no other writer of NAME
lives (in any PID namespace), so a `.NAME.tmp-PID` folder holding only what such a writer
writes (a save cut short) and a `.NAME.old-PID` folder holding such an output (one moved aside)
are a killed writer's: removed at the next write of that folder (an output moved aside and never
replaced is put back first). What counts is the writer's kind (`Debris`): an sfm run never
takes a map for its own, a scene renderer never takes anything but frames it renders.
"""

from __future__ import annotations

import errno
import fcntl
import os
import shutil
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from slamreloc.errors import InputError
from slamreloc.io.outputs import (
    LOCK_HOLDERS,
    lock_file_refusal,
    lock_record,
    make_parents,
    remove_made,
    write_lock_path,
    writer_pid,
)

_HELD: dict[str, int] = {}  # folder -> the thread of this process holding its write lock
_IN_PROCESS: dict[str, threading.Lock] = {}  # folder -> its lock among this process's threads
_GUARD = threading.Lock()  # guards _IN_PROCESS
IN_PROCESS_WAIT_S = 30.0  # how long a thread waits for another of its process (seconds)


@dataclass(frozen=True)
class Debris:
    """What a killed writer of one kind of folder output leaves beside it: `new(folder)` for
    its temporary `.NAME.tmp-PID` (only what it writes there), `old(folder)` for the output it
    had moved aside, `.NAME.old-PID`, with nothing else in it (None: this writer never moves
    one aside), and `put_back(folder)` for such a folder that may go back where NAME is
    missing (it may hold a user's file written into the output meanwhile: put back whole,
    never removed)."""
    new: Callable[[Path], bool]
    old: Callable[[Path], bool] | None
    put_back: Callable[[Path], bool] | None


def _named(out: Path, kind: str) -> list[Path]:
    """The folders beside `out` named exactly `.NAME.KIND-PID` (`writer_pid`): compared as
    strings, not as a pattern (a map named `m[1]` must not take `.m1.tmp-7` for its own), so a
    user's folder of a like name (`.NAME.old-mine`, `.NAME.old-0123`) is never one."""
    try:
        entries = list(os.scandir(out.parent))
    except OSError:  # no folder, or one that cannot be listed: nothing to clean
        return []
    return sorted(Path(e.path) for e in entries
                  if writer_pid(e.name, f".{out.name}.{kind}-") is not None
                  and e.is_dir(follow_symlinks=False))


def holds_only(folder: str | Path, accept: Callable[[os.DirEntry], bool]) -> bool:
    """Whether every entry of `folder` is one `accept` takes (False where it cannot be
    listed): the test of a `Debris` rule, "nothing but what this writer writes"."""
    try:
        return all(accept(entry) for entry in os.scandir(folder))
    except OSError:
        return False


def leftovers(out: Path, debris: Debris) -> list[Path]:
    """What a killed writer of `out` left beside it, and nothing else: `_named` folders that
    hold only what such a writer makes (`debris`). Removed only under the folder's lock
    (`folder_write_lock`), where no writer of it lives."""
    return [path for kind, is_own in (("tmp", debris.new), ("old", debris.old))
            if is_own is not None for path in _named(out, kind) if is_own(path)]


@contextmanager
def folder_write_lock(out: str | Path, what: str, debris: Debris,
                      wait_s: float = IN_PROCESS_WAIT_S) -> Iterator[None]:
    """Hold the exclusive write lock of the folder output `out` (re-entrant within a thread;
    `what` the folder is, one of `LOCK_HOLDERS`, for the message and the lock's record;
    `debris` what its writers leave).

    A second process asking for it gets InputError at once, naming the holder; another
    thread of this process (a server's save, and a load cleaning the same map's leftovers)
    waits for it up to `wait_s` seconds, then gets InputError. On entry, the leftovers of a
    killed writer are cleaned up (and an output it had moved aside is put back)."""
    if what not in LOCK_HOLDERS:  # the record a later writer must recognise
        raise ValueError(f"folder_write_lock: `what` {what!r} is not one of {LOCK_HOLDERS}")
    out = Path(out)
    key = os.path.abspath(out)
    if _HELD.get(key) == threading.get_ident():
        yield
        return
    with _GUARD:
        local = _IN_PROCESS.setdefault(key, threading.Lock())
    if not local.acquire(timeout=wait_s):
        raise InputError(f"{out}: another thread of this process (pid {os.getpid()}) is "
                         f"writing it; try again when it has finished")
    try:
        with _flocked(out, what):
            _HELD[key] = threading.get_ident()
            try:
                _recover(out, debris)
                yield
            finally:
                del _HELD[key]
    finally:
        local.release()


@contextmanager
def _flocked(out: Path, what: str) -> Iterator[None]:
    """Hold `out`'s lock file with `flock` (`_held_lock`), in `out`'s folder, made if missing
    and removed again (with any folder made above it) where the writer wrote nothing."""
    made = make_parents(out)
    try:
        with _held_lock(out, what):
            yield
    finally:
        if not os.path.lexists(out):  # nothing written: no empty folders left behind
            remove_made(made)


@contextmanager
def _held_lock(out: Path, what: str) -> Iterator[None]:
    """Hold `out`'s lock file with `flock` (no other process holds it: InputError naming the
    one that does), its record written; removed when done."""
    lock = write_lock_path(out)
    while True:
        fd = _open_lock(lock, out)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder, theirs = lock_record(fd)
            os.close(fd)
            raise InputError(f"{out}: another process (pid {holder}) is writing {theirs}; "
                             "try again when it has finished") from None
        # the holder before us removes the lock file on release: make sure ours is the
        # file at the path, not one it has just unlinked
        try:
            same = os.path.samestat(os.fstat(fd), os.stat(lock))
        except FileNotFoundError:
            same = False
        if same:
            break
        os.close(fd)
    refusal = lock_file_refusal(out, os.fstat(fd), fd)
    if refusal is not None:
        os.close(fd)
        raise InputError(refusal)
    try:
        try:
            os.ftruncate(fd, 0)
            os.pwrite(fd, f"{os.getpid()}\n{what}\n".encode(), 0)
        except OSError as err:  # a full disk: no lock left behind, the path named
            lock.unlink(missing_ok=True)
            raise OSError(err.errno, err.strerror, str(lock)) from None
        try:
            yield
        finally:
            lock.unlink(missing_ok=True)  # while still holding it (see above)
    finally:
        os.close(fd)  # releases the lock


def _open_lock(lock: Path, out: Path) -> int:
    """The lock file's descriptor, created if absent; a symbolic link, a hard link (a file of
    several names), a FIFO, a device or a folder at its path is refused, never followed,
    written or waited on."""
    try:
        fd = os.open(lock, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_NONBLOCK
                     | os.O_CLOEXEC, 0o644)
    except OSError as err:
        if err.errno in (errno.ELOOP, errno.EISDIR, errno.ENXIO):
            raise InputError(f"{lock}: not a regular file (a link, folder or device); "
                             f"refusing to use it as the write lock of {out.name}") from None
        raise
    refusal = lock_file_refusal(out, os.fstat(fd))  # its record is read once it is held
    if refusal is not None:
        os.close(fd)
        raise InputError(refusal)
    return fd


def _recover(out: Path, debris: Debris) -> None:
    """Under the lock: put back an output a killed writer had moved aside; remove its
    leftovers."""
    olds = [p for p in _named(out, "old") if debris.put_back is not None and debris.put_back(p)]
    if olds and not os.path.lexists(out):
        newest = max(olds, key=lambda p: p.stat().st_mtime)
        os.replace(newest, out)
        fsync_dir(out.parent)
    for p in leftovers(out, debris):
        shutil.rmtree(p, ignore_errors=True)


def fsync_dir(path: Path) -> None:
    """Make a folder's entries (renames, new files) durable."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
