"""A command's outputs, written so that nothing the user had is lost or left half-written:
where they may go (`check_outputs`), each atomically (`atomic_file`, `write_json`), all of a
command's as one (`outputs_together`), and what a killed writer left beside them
(`remove_dead_leftovers`)."""

from __future__ import annotations

import errno
import json
import os
import re
import stat
import tempfile
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

from slamreloc.errors import InputError
from slamreloc.io.fileio import (disk_identities, file_identity, file_kind, is_link_loop,
                                 relation, relation_on_disk, resolved, stat_or_none)


def _own_test(value) -> tuple:
    """`check_outputs`' folder or file entry as (is_own or None or ..., the kind's name or
    None)."""
    return value if isinstance(value, tuple) else (value, None)


def _check_writable(out: Path, option: str) -> None:
    """InputError naming `option` unless a file can be created where `out` goes: a probe
    created in the nearest existing folder of its path (unnamed where the file system allows,
    so that a kill leaves no probe behind) and removed (a read-only or pseudo file system,
    /proc or /sys, refuses it there, not after the work)."""
    folder = next((p for p in (out.parent, *out.parent.parents) if os.path.isdir(p)), None)
    if folder is None:
        return
    try:
        try:  # an unnamed file (O_TMPFILE): a kill -9 here leaves nothing in the folder
            os.close(os.open(folder, os.O_TMPFILE | os.O_WRONLY, 0o600))
        except OSError as err:  # a file system without unnamed files: a named probe
            if err.errno not in (errno.EOPNOTSUPP, errno.EISDIR, errno.EINVAL):
                raise
            fd, name = tempfile.mkstemp(prefix=f".{out.name}.probe-", dir=folder)
            os.close(fd)
            os.unlink(name)
    except OSError as err:
        raise InputError(f"{out}: {option} cannot be written there ({folder}: "
                         f"{err.strerror or err})") from None


def reads_as(read: Callable[[Path], object], kind: str) -> tuple[Callable[[Path], bool], str]:
    """`check_outputs`' `files` entry of an output that may replace only a file of its own
    `kind`: one that `read` reads without an InputError (any other file there is the user's)."""
    def is_own(path: Path) -> bool:
        try:
            read(path)
        except InputError:
            return False
        return True

    return is_own, kind


def marked_file(signature: bytes, marker: bytes, kind: str
                ) -> tuple[Callable[[Path], bool], str]:
    """`check_outputs`' `files` entry of a binary output slamreloc marks as its own: a file
    may be replaced only if it starts with `signature` and holds `marker` in its first 4 KB
    (a PLY header's comment, a PNG's text chunk); any other file there is the user's."""
    def is_own(path: Path) -> bool:
        try:
            with open(path, "rb") as f:
                head = f.read(4096)
        except OSError:
            return False
        return head.startswith(signature) and marker in head

    return is_own, kind


def write_lock_path(out: str | Path) -> Path:
    """The lock file of a folder being written (`.NAME.lock` beside it): held by the writer
    of a folder output (`slamreloc.io.folder_lock.folder_write_lock`) while it works."""
    out = Path(out)
    return out.parent / f".{out.name}.lock"


def lock_record(fd: int, wait_s: float = 1.0) -> tuple[str, str]:
    """(process id, what it writes) as a live writer records them in its lock file
    ("PID\nWHAT\n"). A writer writes its record just after it takes the lock: one met in
    between is read again for up to `wait_s` seconds, then told as ("?", "this folder")."""
    deadline = time.monotonic() + wait_s
    while True:
        text = os.pread(fd, 256, 0).decode(errors="replace")
        pid, _, what = text.partition("\n")
        if what.endswith("\n") and pid.strip() and what.strip():
            return pid.strip(), what.strip()
        if time.monotonic() > deadline:
            return pid.strip() or "?", what.strip() or "this folder"
        time.sleep(0.01)


# what a lock records its writer writes (its WHAT)
LOCK_HOLDERS = ("this map", "this dataset", "this COLMAP model", "this scene")


def lock_record_or_empty(fd: int) -> bool:
    """Whether the lock file is empty or holds exactly a writer's record ("PID\nWHAT\n", PID
    as a process id is written, WHAT one of `LOCK_HOLDERS`), as a killed writer leaves it:
    anything else is a user's file of that name (`2024\nbudget\n`)."""
    size = os.fstat(fd).st_size
    if size == 0:
        return True
    if size > 256:
        return False
    text = os.pread(fd, size, 0)
    pid, _, what = text.partition(b"\n")
    return (writer_pid(pid.decode("ascii", "replace"), "") is not None
            and what.endswith(b"\n") and what[:-1].decode("ascii", "replace") in LOCK_HOLDERS)


def mount_table() -> list[tuple[str, str, str]]:
    """(device "major:minor", the mounted folder's path within the device, the mount point)
    of each mount this process sees (/proc/self/mountinfo, its octal escapes of blanks, tabs,
    line breaks and backslashes undone); [] where there is no mount table."""
    try:
        with open("/proc/self/mountinfo", encoding="utf-8", errors="replace") as table:
            rows = [line.split() for line in table]
    except OSError:
        return []

    def unescaped(text: str) -> str:
        return re.sub(r"\\([0-7]{3})", lambda m: chr(int(m.group(1), 8)), text)

    return [(r[2], unescaped(r[3]), unescaped(r[4])) for r in rows if len(r) > 4]


def is_mount_point(path: str | Path) -> bool:
    """Whether `path` is a mount point: another file system (`os.path.ismount`) or a bind
    mount of the same one, which only the mount table tells."""
    if os.path.ismount(path):
        return True
    where = os.path.realpath(path)
    return any(point == where for _, _, point in mount_table())


def lock_file_refusal(out: str | Path, info: os.stat_result, fd: int | None = None
                      ) -> str | None:
    """Why the file at `out`'s lock path (`write_lock_path`; `info` its lstat or fstat, `fd`
    open on it where its record is to be read) cannot be `out`'s write lock, or None: a link,
    folder, pipe or device; a file of several names (its record would change another file);
    a file that is neither empty nor a writer's record (a user's)."""
    lock, name = write_lock_path(out), Path(out).name
    if not stat.S_ISREG(info.st_mode):
        return (f"{lock}: not a regular file (a link, folder or device); refusing to use it "
                f"as the write lock of {name}")
    if info.st_nlink != 1:
        return (f"{lock}: a file with {info.st_nlink} names (hard links); refusing to use it "
                f"as the write lock of {name}")
    if fd is not None and not lock_record_or_empty(fd):
        return (f"{lock}: holds something that is not a slamreloc write lock; refusing to "
                f"overwrite it (move it to write {name})")
    return None


def lock_file_problem(out: str | Path) -> str | None:
    """`lock_file_refusal` of what is at `out`'s lock path now, None where nothing is: what
    the folder's writer would refuse when it takes the lock, said before the work."""
    lock = write_lock_path(out)
    try:
        info = os.lstat(lock)
    except OSError:
        return None
    if not stat.S_ISREG(info.st_mode) or info.st_nlink != 1:
        return lock_file_refusal(out, info)
    try:
        fd = os.open(lock, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC)
    except OSError:  # gone meanwhile, or unreadable: the writer says why
        return None
    try:
        return lock_file_refusal(out, os.fstat(fd), fd)
    finally:
        os.close(fd)


def busy_writer(out: str | Path) -> str | None:
    """`FOLDER: another process (pid N) is writing WHAT; ...` where a live writer (another
    process than this one) holds `out`'s write lock, else None."""
    import fcntl

    try:
        fd = os.open(write_lock_path(out), os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK)
    except OSError:  # none, or a link: no writer's lock (a writer refuses a link)
        return None
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except BlockingIOError:
            pid, what = lock_record(fd)
            if pid == str(os.getpid()):  # this process's own
                return None
            return (f"{out}: another process (pid {pid}) is writing {what}; try again when it "
                    "has finished")
        except OSError:
            return None
        fcntl.flock(fd, fcntl.LOCK_UN)
        return None
    finally:
        os.close(fd)


# the names writers work under beside an output (`temp_file_path`, `temp_dir_path`,
# `write_lock_path`): never an output's own name
WRITERS_NAME = re.compile(r"\..+\.(?:(?:tmp|old)-([1-9][0-9]*)(?:\..*)?|lock)", re.DOTALL)


def is_writers_name(name: str) -> bool:
    """Whether `name` is one a writer works under beside its output (`WRITERS_NAME`, its PID
    one Linux can give)."""
    match = WRITERS_NAME.fullmatch(name)
    return match is not None and (match.group(1) is None or int(match.group(1)) <= PID_LIMIT)


# the longest of those beside NAME: `.NAME.train-checkpoint.pt`, `.NAME.names.old-PID.txt`...
WORKING_NAME_EXTRA = 32
MAX_OUTPUT_NAME = 255 - WORKING_NAME_EXTRA


LINK_WALK_ENTRIES = 1_000_000  # entries of an input folder looked at for links (a 7-Scenes
# scene of 7 x 1000 frames holds ~21 000)
LINK_WALK_S = 5.0  # and seconds at most (about 1 s for a million plain entries)


@dataclass
class InputReach:
    """Where a command that reads an input folder reads: `linked`, the folders outside it that
    its symbolic links lead to (a linked folder, the folder holding a linked file);
    `mounted`, the sources of the folders bind-mounted inside it; and `folders`, (device,
    inode) -> a path, of every folder walked inside it or through its links (a bind-mounted
    sequence is the same folder on disk as its source)."""

    linked: list[Path]
    folders: dict[tuple[int, int], Path]
    mounted: list[Path] = field(default_factory=list)  # `bind_mount_sources`


def bind_mount_sources(folder: Path) -> list[Path]:
    """The folders mounted at or inside `folder` under another name (bind mounts, on Linux),
    as this process sees them: where each one's files are found outside `folder`. Read from
    the mount table, so no walk of `folder` is needed. [] where there is no mount table."""
    mounts = mount_table()
    root = resolved(folder)
    out = []
    for device, source_root, point in mounts:
        if not Path(point).is_relative_to(root):
            continue
        # where the same device's `source_root` is reachable: a mount of it whose own root
        # holds `source_root` (the device's whole file system at /, typically)
        for other_device, other_root, other_point in mounts:
            if other_device == device and other_point != point and \
                    Path(source_root).is_relative_to(other_root):
                source = Path(other_point) / Path(source_root).relative_to(other_root)
                if not source.is_relative_to(root):
                    out.append(source)
                break
    return out


def _link_target(path: str) -> Path:
    """Where the symbolic link `path` leads, resolved by the kernel in one call (Linux: the
    path of an O_PATH descriptor of it) rather than one path part at a time; a link to
    nothing: its text joined to its folder."""
    try:
        fd = os.open(path, getattr(os, "O_PATH", os.O_RDONLY) | os.O_CLOEXEC)
    except OSError:
        try:
            return Path(os.path.normpath(os.path.join(os.path.dirname(path),
                                                      os.readlink(path))))
        except OSError:
            return Path(os.path.abspath(path))
    try:
        return Path(os.readlink(f"/proc/self/fd/{fd}"))
    except OSError:
        return resolved(path)
    finally:
        os.close(fd)


def input_reach(folder: Path, limit: int = LINK_WALK_ENTRIES,
                time_s: float = LINK_WALK_S) -> InputReach:
    """`InputReach` of `folder`, walked breadth first at any depth and through the folders
    its links lead to, each folder once (a loop of links ends), plus the sources of the
    folders bind-mounted inside it (`bind_mount_sources`, from the mount table: complete
    whatever the walk's size). The walk looks at `limit` entries at most, for `time_s`
    seconds at most: links beyond that are not followed. Empty for a file or a folder that
    cannot be listed."""
    found: set[Path] = set()
    folders: dict[tuple[int, int], Path] = {}
    pending, seen = deque([Path(folder)]), 0
    stop_at = time.monotonic() + time_s
    while pending and seen < limit and time.monotonic() < stop_at:
        here = pending.popleft()
        try:
            st = os.stat(here)
            if not stat.S_ISDIR(st.st_mode) or (st.st_dev, st.st_ino) in folders:
                continue
            folders[st.st_dev, st.st_ino] = here
            with os.scandir(here) as entries:
                for entry in entries:
                    seen += 1
                    if seen > limit or seen % 1024 == 0 and time.monotonic() >= stop_at:
                        break
                    if entry.is_symlink():
                        target = _link_target(entry.path)
                        if entry.is_dir():  # walked too: a link inside it leads further
                            found.add(target)
                            pending.append(Path(entry.path))
                        else:
                            found.add(target.parent)
                    elif entry.is_dir(follow_symlinks=False):
                        pending.append(Path(entry.path))
        except OSError:
            continue
    root = resolved(folder)
    mounted = bind_mount_sources(folder) if Path(folder).is_dir() else []
    return InputReach(sorted(f for f in found if not f.is_relative_to(root)), folders, mounted)


def check_outputs(outputs: dict[str, str | Path | None],
                  inputs: dict[str, str | Path | None],
                  folders: tuple[str, ...] | dict[str, Callable[[Path], bool] | None] = (),
                  files: dict[str, Callable[[Path], bool] | tuple] | None = None) -> None:
    """A command never writes where it only reads, nor over something that is not its own kind
    of output. InputError, before any work, unless each output path (keyed by how the user
    named it, e.g. "--report") is apart from every input (keyed by what it is, e.g. "the map":
    not the same file, not inside an input folder, not a folder holding one), apart from the
    other outputs (not the same path, not inside another output, not holding one), under
    folders only (no parent is a file, a pipe or a device), writable there (a probe file is
    created and removed: /proc, /sys, a read-only folder are refused now, not after the work),
    and absent or a regular file (a folder for the outputs named in `folders`): never a device,
    a pipe or a socket (`/proc/self/fd/1`), which an atomic rename would replace, nor a
    non-empty folder that is not already that output's kind
    (`folders` as a dict: option -> `is_own(folder)`, True for a folder the output may
    replace, or `(is_own, "a slamreloc map")` to name that kind in the message; None: only an
    empty folder; a tuple: any folder), nor (`files`: option -> `is_own(file)` or
    `(is_own, "a frame-names file")`) an existing file that is not that option's kind. The
    temporary path `atomic_file` writes beside a file output must not be anything but a
    regular file either, nor be there at all beside a folder output (`temp_dir_path`). An
    output that is itself a symbolic link is refused (the rename would
    replace the link: `/dev/stdout` is one); links among its parent folders are followed."""
    ins = {what: resolved(p) for what, p in inputs.items() if p is not None}  # loops too
    # each input also as named (an output named through it, leaving it by a link inside it:
    # DATASET/seq-01/x where seq-01 is a link) and the folders linked into an input folder
    # (a sequence kept on another disk: its frames are what the command reads)
    named = {what: Path(os.path.abspath(p)) for what, p in inputs.items() if p is not None}
    reach = {what: input_reach(src) for what, src in ins.items()}
    own = folders if isinstance(folders, dict) else dict.fromkeys(folders, ...)
    working = {}  # the paths each output's writer works in beside it (lock, temporaries)
    for option, out in outputs.items():
        if out is not None:
            out = Path(out)
            for role, path in ((("lock file", write_lock_path(out)),
                                ("temporary folder", temp_dir_path(out)),
                                ("old copy", temp_dir_path(out, "old"))) if option in own else
                               (("temporary file", temp_file_path(out)),
                                ("old copy", temp_file_path(out, "old")))):
                working[resolved(path)] = f"{option}'s {role}"
    seen: dict[Path, str] = {}
    for option, out in outputs.items():
        if out is None:
            continue
        if str(out) == "-":  # a user's hope for standard output, not a file named "-"
            raise InputError(f"-: {option} must name a path; '-' (standard output) is not "
                             "taken here")
        target = resolved(out)
        if target in working:
            raise InputError(f"{out}: {option} is {working[target]}, which its writer makes "
                             "and removes; write it elsewhere")
        if Path(out).name in ("", ".", ".."):  # its lock and temporaries would go inside it
            raise InputError(f"{out}: {option} must end in a name, not '.' or '..' (give the "
                             "folder's path from its parent, e.g. ../NAME)")
        if is_writers_name(Path(out).name):  # a later writer beside it would remove it
            raise InputError(f"{out}: {option} is named as a writer's temporary or lock "
                             "(.NAME.tmp-PID, .NAME.old-PID, .NAME.lock), which writers "
                             "remove; give another name")
        size = len(os.fsencode(Path(out).name))
        if size > MAX_OUTPUT_NAME:  # the writer's own names beside it must fit too
            raise InputError(f"{out}: {option}'s name is {size} bytes; at most "
                             f"{MAX_OUTPUT_NAME} (its writer's temporaries beside it, "
                             f"{WORKING_NAME_EXTRA} bytes longer, must fit the file system's "
                             "255)")
        for other, option_other in seen.items():
            if target == other:
                raise InputError(f"{out}: {option} and {option_other} name the same path")
            if target.is_relative_to(other) or other.is_relative_to(target):
                inner, outer = ((option, option_other) if target.is_relative_to(other)
                                else (option_other, option))
                raise InputError(f"{out}: {inner} would lie inside {outer}; two outputs of one "
                                 "command never overlap")
        seen[target] = option
        dangling = next((p for p in Path(out).absolute().parents
                         if os.path.islink(p) and not p.exists()), None)
        if dangling is not None:  # a folder made there would fail only after the work
            raise InputError(f"{out}: {option} cannot be written there: its parent {dangling} "
                             + ("is a symbolic link loop" if is_link_loop(dangling) else
                                f"is a symbolic link to {os.readlink(dangling)[:200]}, which "
                                "does not exist"))
        parent = next((p for p in target.parents if p.exists()), None)
        if parent is not None and not parent.is_dir():
            kind = "a file" if parent.is_file() else "not a folder"
            raise InputError(f"{out}: {option} cannot be written there: its parent {parent} is "
                             f"{kind}")
        busy = busy_writer(out) or (lock_file_problem(out) if option in own else None)
        if busy is not None:  # a map (or sfm dataset) being written there right now, or a
            raise InputError(busy)  # lock path its writer would refuse
        on_disk = disk_identities(target)
        for what, src in ins.items():
            how = relation_on_disk(target, src)
            if how is None and src.is_dir():
                how = relation(Path(os.path.abspath(out)), named[what])
                if how is None:
                    link = next((f for f in reach[what].linked if relation(target, f)), None)
                    mount = next((f for f in reach[what].mounted if relation(target, f)), None)
                    if link is not None:
                        how, src = relation(target, link), link
                        what = f"{what}'s linked folder"
                    elif mount is not None:
                        how, src = relation(target, mount), mount
                        what = f"{what}'s bind-mounted folder"
                if how is None:  # a folder inside the input under another name (a bind mount)
                    up, inside = next(((up, reach[what].folders[i]) for up, i in on_disk
                                       if i in reach[what].folders), (None, None))
                    if inside is not None:
                        raise InputError(
                            f"{out}: {option} lies inside {(target, *target.parents)[up]}, "
                            f"which is {what}'s folder {inside} under another name (the same "
                            "folder on disk), which this command only reads; write it "
                            "elsewhere")
            if how is None or how == "lies inside" and not src.is_dir():
                continue
            where = what if how == "is" else f"{what} ({src})"
            raise InputError(f"{out}: {option} {how} {where}, which this command only reads; "
                             "write it elsewhere")
        want_dir = option in own
        if os.path.islink(out):  # /dev/stdout, or a link to /proc/self/fd/1: never renamed over
            link = os.readlink(out)
            raise InputError(f"{out}: {option} is a symbolic link (to {link[:200]}); writing "
                             "would replace the link, not what it points to: give a plain "
                             "path")
        st = stat_or_none(Path(out))
        if st is not None:
            is_dir, is_file = stat.S_ISDIR(st.st_mode), stat.S_ISREG(st.st_mode)
            if want_dir and not is_dir or not want_dir and not is_file:
                kind = file_kind(st.st_mode)
                kind = kind if kind in ("a folder", "a file") else f"not a regular file ({kind})"
                raise InputError(f"{out}: {option} exists and is {kind}; refusing to replace it")
            if is_mount_point(out):  # a container's volume: the rename would fail (EBUSY)
                raise InputError(f"{out}: {option} is a mount point; its writer puts the new "
                                 f"{'folder' if want_dir else 'file'} in by a rename over it, "
                                 "which a mount point does not allow: give a path inside it")
            is_own, own_kind = _own_test(own.get(option, ...))
            if want_dir and is_own is not ... and any(target.iterdir()) and (
                    is_own is None or not is_own(target)):
                if is_own is None:  # an output that never replaces a folder, even its own
                    raise InputError(f"{out}: {option} exists and is not empty; this command "
                                     "writes a new or an empty folder only, never over one "
                                     "(choose another, or remove it)")
                raise InputError(f"{out}: {option} exists, is not empty and is not "
                                 f"{own_kind or 'its own output'}; "
                                 "refusing to replace it (give a new or an empty folder)")
            is_own, own_kind = _own_test((files or {}).get(option, ...))
            if not want_dir and is_own is not ... and not is_own(Path(out)):
                raise InputError(f"{out}: {option} exists and is not "
                                 f"{own_kind or 'this output'}; refusing to replace it (move "
                                 "it or write elsewhere)")
        # its writer's temporary and (a file's) second name: refused now, not after the work
        for tmp in ((temp_dir_path(out),) if want_dir else
                    (temp_file_path(Path(out)), temp_file_path(Path(out), "old"))):
            if os.path.lexists(tmp) and (want_dir or not _unheld_file(tmp)):
                raise InputError(temp_in_the_way(tmp, f"{out}: {option}"))
        _check_writable(Path(out), option)
        record_checked(out)


# what each output `check_outputs` passed was at that check: itself (None: absent) and its
# folder; its writer puts it in place only where neither has changed since
# (`still_as_checked`) and records what it put there (`record_written`)
_CHECKED: dict[Path, tuple[tuple[int, ...] | None, tuple[int, ...] | None]] = {}


def record_checked(out: str | Path) -> None:
    """Remember what the output `out` and its folder are now (at `check_outputs`), for
    `still_as_checked`."""
    key = Path(os.path.abspath(out))
    _CHECKED[key] = (file_identity(key, False), file_identity(key.parent))


def record_written(out: str | Path) -> None:
    """After a writer put `out` in place: what is there now is its own (for its next write).
    Only outputs `check_outputs` checked are followed: a writer that did not check (a
    library caller's, a server's) is not bound by an earlier write of the same path."""
    if Path(os.path.abspath(out)) in _CHECKED:
        record_checked(out)


def still_as_checked(out: str | Path) -> None:
    """InputError, naming `out`, where the output or its folder is no longer what
    `check_outputs` (or its writer's last write) saw: a file, a folder, a link or a pipe put
    at `out`, or its folder swapped for another (a link) while the command ran. Its writer
    then puts nothing in place and what is there is kept. An output removed meanwhile may be
    written; an output never checked (a library caller's) passes."""
    key = Path(os.path.abspath(out))
    if key not in _CHECKED:
        return
    was, folder = _CHECKED[key]
    if folder is not None and file_identity(key.parent) != folder:  # (None: made since)
        raise InputError(f"{out}: its folder {key.parent} was replaced while the command ran; "
                         "not written (what is there is kept)")
    now = file_identity(key, False)
    if now is not None and now != was:
        raise InputError(f"{out}: {what_is_there(key)} was put there while the command ran; "
                         "not written (what is there is kept)")


def what_is_there(path: Path) -> str:
    """What is at `path` now, not following a link, in words ("a symbolic link (to X)", "a
    file", "a named pipe", ...)."""
    try:
        if os.path.islink(path):
            return f"a symbolic link (to {os.readlink(path)[:200]})"
        return file_kind(os.lstat(path).st_mode)
    except OSError:
        return "nothing"


_together = threading.local()  # .pending: the commits of an `outputs_together` block


@contextmanager
def outputs_together() -> Iterator[None]:
    """Write a command's several outputs as one: each writer inside the block (`atomic_file`,
    `save_map`, any `commit_output`) writes its temporary, and the renames that put them in
    place run only when the whole block has succeeded. A failure or a Ctrl-C inside (a full
    disk at the second file) removes every temporary and leaves all outputs as they were; a
    Ctrl-C or SIGTERM that arrives during the renames is held until they are done, then
    raised (KeyboardInterrupt). So a command's outputs are all new or all as they were, never
    a new report beside an old plot. The block may hold the work that makes the outputs (it is
    interrupted as usual); a write inside it that must land at once (a periodic checkpoint)
    goes in `outputs_now`. Nested blocks commit with the outermost; off the main thread
    signals are not held. Files are renamed in first, folders (a map) last: a kill -9, which
    nothing can hold, landing among the renames (milliseconds) leaves some files new beside
    the old map, never the new map with its old report; the temporaries it leaves are
    removed by the next writer of each output (`remove_dead_leftovers`)."""
    if _pending() is not None:
        yield
        return
    pending: list[tuple[Callable[[], Undo], Callable[[], None], bool]] = []
    _together.pending = pending
    done = False
    try:
        yield
        done = True
    finally:
        _together.pending = None
        with signals_held():
            undos: list[Undo] = []
            try:  # folders (a map) last: a kill -9 between renames leaves the old map
                for commit, _, _ in sorted(pending, key=lambda c: c[2]) if done else ():
                    undos.append(commit())
            except BaseException:  # a rename refused (a file made immutable meanwhile): the
                for undo in reversed(undos):  # outputs already in place go back as they were
                    if undo is not None:
                        undo()
                raise
            finally:
                for _, discard, _ in pending:
                    discard()


@contextmanager
def outputs_now() -> Iterator[None]:
    """Inside an `outputs_together` block, the writers in this one put their outputs in place
    at once, not with the block (a checkpoint that must survive a crash, or what an
    interrupted command saves on its way out)."""
    pending = _pending()
    _together.pending = None
    try:
        yield
    finally:
        _together.pending = pending


@contextmanager
def signals_held() -> Iterator[None]:
    """A Ctrl-C or SIGTERM arriving inside the block waits for its end, then is raised
    (KeyboardInterrupt) unless the block raised; off the main thread nothing is held."""
    import signal

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    held: list[int] = []
    previous = {s: signal.signal(s, lambda signum, frame: held.append(signum))
                for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
    if held:
        raise KeyboardInterrupt


Undo = Callable[[], None] | None  # what puts an output back as it was before its commit


def _pending() -> list | None:
    """The commits of the `outputs_together` block this thread is in (None: none)."""
    return getattr(_together, "pending", None)


def commit_output(commit: Callable[[], Undo], discard: Callable[[], None],
                  folder: bool = False) -> None:
    """Put a written output in place: `commit()` (a rename) now, or, inside `outputs_together`,
    when the whole block has succeeded (a `folder` after the files); `discard()` (removing
    what `commit` did not take, and the old copy it kept) runs after it either way. `commit`
    returns how to undo it (None: nothing to undo), used where a later output of the block
    cannot be put in place."""
    pending = _pending()
    if pending is not None:
        pending.append((commit, discard, folder))
        return
    try:
        commit()
    finally:
        discard()


def temp_file_path(path: Path, role: str = "tmp") -> Path:
    """The temporary file `atomic_file` writes `path` into: hidden beside it, named with this
    process id, with `path`'s suffix (a writer that picks its format by suffix keeps it); with
    `role` "old", the second name it keeps the replaced file under until its block is done."""
    return path.with_name(f".{path.stem}.{role}-{os.getpid()}{path.suffix}")


def temp_dir_path(out: str | Path, role: str = "tmp") -> Path:
    """The folder a writer of the folder `out` works in: `.NAME.tmp-PID` (the new contents
    before they are renamed in), or with `role` "old" `.NAME.old-PID` (the old contents moved
    aside); hidden beside `out`, named with this process id."""
    out = Path(out)
    return out.parent / f".{out.name}.{role}-{os.getpid()}"


def temp_in_the_way(tmp: Path, what: str) -> str:
    """The refusal of a writer whose temporary path (named with its process id) is taken: by
    a user's file, a link, or a killed writer's leftover whose process id this one has again
    (as in a container). None of them is this process's to delete or write through."""
    return (f"{what} cannot be written: its temporary path {tmp} is in the way, and not made "
            "by this process (a user's, a killed writer's with this process id, or a live "
            "writer's in another PID namespace, as in a container); refusing to delete or "
            "write through it (move it, or try again when that writer has finished)")


@contextmanager
def naming_output(path: str | Path) -> Iterator[None]:
    """An OSError raised while the output `path` is written that names no file (a full disk:
    `[Errno 28] No space left on device`) is raised again naming `path`."""
    try:
        yield
    except OSError as err:
        if err.filename is None and err.errno is not None:
            raise OSError(err.errno, err.strerror or str(err), str(path)) from None
        raise


def make_parents(path: str | Path) -> list[Path]:
    """Make the missing folders above `path` (as `mkdir -p` would) and return those this
    call made, outermost first: only they may be removed again (`remove_made`)."""
    missing = []
    parent = Path(path).parent
    while not os.path.lexists(parent) and parent != parent.parent:
        missing.append(parent)
        parent = parent.parent
    made = []
    for folder in reversed(missing):
        try:
            os.mkdir(folder)
            made.append(folder)
        except FileExistsError:  # made meanwhile by someone else: theirs
            pass
    Path(path).parent.mkdir(parents=True, exist_ok=True)  # its usual errors, path named
    return made


def remove_made(folders: list[Path]) -> None:
    """Remove the folders `make_parents` made, innermost first, where they are still empty
    (a command that wrote nothing leaves no empty folders behind; anything put in one keeps
    it and those above it)."""
    for folder in reversed(folders):
        try:
            os.rmdir(folder)
        except OSError:  # not empty, or gone: keep the rest
            return


def make_temp_dir(tmp: Path, what: str) -> Path:
    """Make the writer's temporary folder `tmp` (named with this process id) beside its
    output `what`: a new folder, never an existing path (`temp_in_the_way`), which a writer
    removes only after making it here."""
    try:
        os.mkdir(tmp)
    except FileExistsError:
        raise InputError(temp_in_the_way(tmp, what)) from None
    return tmp


@contextmanager
def atomic_file(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path beside `path` (same suffix), made here as a new empty file
    (never an existing one, nor through a link: `temp_in_the_way`); rename it over `path` on
    success (inside `outputs_together`, when the whole block succeeds), remove it on
    failure. The temporary, and the second name the replaced file is kept under inside a
    block, are held with an exclusive `flock` while this writer lives: what a killed writer
    left (no process holds it, whatever its process id or PID namespace) is removed by the
    next writer (`remove_dead_leftovers`), a live writer's never. Folders made above `path`
    are removed again where nothing was written (`remove_made`)."""
    path = Path(path)
    made = make_parents(path)
    remove_dead_leftovers(path)
    tmp = temp_file_path(path)
    held = [(tmp, _create_held(tmp, str(path)))]  # this writer's files, each with its lock
    backup = temp_file_path(path, "old")
    undoable = _pending() is not None  # only a block's outputs may need putting back

    def replace() -> Undo:  # the old file kept (a second name) until the block is done
        kept = False
        with naming_output(path):
            still_as_checked(path)
            existed = os.path.lexists(path)
            if undoable and os.path.isfile(path) and not os.path.islink(path):
                held.append((backup, _keep_old(path, backup)))
                kept = True
            os.replace(tmp, path)
            record_written(path)
        if kept:
            return lambda: os.replace(backup, path)
        return None if existed else lambda: path.unlink(missing_ok=True)

    def discard() -> None:
        try:
            for name, fd in held:  # a name still this writer's file (not renamed away, nor
                if _same_file(fd, name):  # made again by a writer of the same PID elsewhere)
                    name.unlink()
        finally:
            for _, fd in held:
                os.close(fd)  # releases its lock
            if not os.path.lexists(path):  # nothing written: no empty folders left behind
                remove_made(made)

    try:
        with naming_output(path):
            yield tmp
    except BaseException:
        discard()
        raise
    commit_output(replace, discard)


def _create_held(path: Path, what: str) -> int:
    """A new empty file at `path` (never an existing one, nor through a link), held with an
    exclusive `flock` on the returned descriptor; made again where a cleaner removed the new
    file before it was locked."""
    import fcntl

    for _ in range(8):
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW
                         | os.O_CLOEXEC, 0o644)
        except FileExistsError:
            raise InputError(temp_in_the_way(path, what)) from None
        fcntl.flock(fd, fcntl.LOCK_EX)  # a cleaner holds it for an instant at most
        if _same_file(fd, path):
            return fd
        os.close(fd)  # removed meanwhile as a dead writer's: make it again
    raise InputError(temp_in_the_way(path, what))


def _same_file(fd: int, path: Path) -> bool:
    try:
        return os.path.samestat(os.fstat(fd), os.lstat(path))
    except FileNotFoundError:
        return False


def _keep_old(path: Path, backup: Path) -> int:
    """Keep the file at `path` under the second name `backup` until the block is done, and
    return the descriptor that holds `backup` (an exclusive `flock`): a hard link where the
    file system makes them and nobody else locks the file, else a copy of its bytes and mode.
    InputError where `backup` is taken (by a live writer's: another process writing this
    output)."""
    import fcntl

    for _ in range(8):
        try:
            os.link(path, backup, follow_symlinks=False)
        except FileExistsError:
            raise InputError(temp_in_the_way(backup, str(path))) from None
        except OSError as err:
            if err.errno not in (errno.EPERM, errno.EXDEV, errno.EMLINK, errno.ENOTSUP,
                                 errno.EOPNOTSUPP):
                raise
            break  # no links here: a copy
        fd = os.open(backup, os.O_RDONLY | os.O_NOFOLLOW | os.O_CLOEXEC)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:  # the user's file is locked by another program: a copy
            os.close(fd)
            os.unlink(backup)
            break
        if _same_file(fd, backup):
            return fd
        os.close(fd)  # removed meanwhile as a dead writer's: link it again
    fd = _create_held(backup, str(path))
    try:
        with open(path, "rb") as src:
            os.fchmod(fd, os.fstat(src.fileno()).st_mode & 0o7777)
            for chunk in iter(lambda: src.read(1 << 20), b""):
                os.write(fd, chunk)
    except BaseException:
        os.close(fd)
        backup.unlink(missing_ok=True)
        raise
    return fd


def writer_pid(name: str, prefix: str, suffix: str = "") -> int | None:
    """The process id in a writer's temporary name `PREFIX` + PID + `SUFFIX`, compared as
    strings (never a pattern), or None where `name` is not such a name: PID as a process id
    is written, digits with no leading zero, a process id Linux can give (1 to 2**22: a
    dated backup `.m.old-20240101`, `.r.old-0123.json` are a user's names)."""
    if not (name.startswith(prefix) and name.endswith(suffix)
            and len(name) > len(prefix) + len(suffix)):
        return None
    pid = name[len(prefix):len(name) - len(suffix)]
    if not (pid.isascii() and pid.isdigit()) or pid != str(int(pid)) \
            or not 0 < int(pid) <= PID_LIMIT:
        return None
    return int(pid)


PID_LIMIT = 1 << 22  # Linux's largest process id (PID_MAX_LIMIT), whatever this system's


def is_file_debris_name(name: str, path: Path) -> bool:
    """Whether `name` is exactly one `atomic_file`'s writers of the file `path` work under
    beside it: `.STEM.tmp-PID.SUFFIX` or `.STEM.old-PID.SUFFIX` (PID as `writer_pid` takes
    it)."""
    return any(writer_pid(name, f".{path.stem}.{role}-", path.suffix) is not None
               for role in ("tmp", "old"))


def _lock_unheld(path: str | Path) -> int | None:
    """A descriptor of the regular file at `path` (not a link, a device or a pipe, which is
    never opened) locked with an exclusive `flock`, where no process holds it; else None."""
    import fcntl

    try:
        if not stat.S_ISREG(os.lstat(path).st_mode):
            return None
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC)
    except OSError:  # gone, a link, or not ours to open
        return None
    try:
        if stat.S_ISREG(os.fstat(fd).st_mode):
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            return fd
    except OSError:  # held by a live writer
        pass
    os.close(fd)
    return None


def _unheld_file(path: Path) -> bool:
    """Whether `path` is a regular file (not a link) that no process holds with `flock`: a
    killed writer's temporary, which the next writer removes (`remove_dead_leftovers`)."""
    fd = _lock_unheld(path)
    if fd is None:
        return False
    os.close(fd)
    return True


def remove_dead_leftovers(path: str | Path) -> list[Path]:
    """Remove what a killed writer (kill -9, a power cut) of the file `path` left beside it:
    regular files named exactly `.STEM.tmp-PID.SUFFIX` (its unfinished or uncommitted new
    file) or `.STEM.old-PID.SUFFIX` (the second name it kept of the file it replaced) that
    no process holds (`atomic_file` holds its own with `flock` while it lives, so this works
    across PID namespaces and whatever the PID). A link, a folder, a live writer's file or a
    user's file of another name (`.r.old-mine.json`, `.r.old-0123.json`) is never taken.
    Returns what was removed."""
    path = Path(path)
    try:
        entries = list(os.scandir(path.parent))
    except OSError:  # no folder, or one that cannot be listed: nothing to clean
        return []
    removed = []
    for entry in entries:
        if not is_file_debris_name(entry.name, path):
            continue
        fd = _lock_unheld(entry.path)
        if fd is None:
            continue
        try:
            if _same_file(fd, Path(entry.path)):  # still the file locked, not a new one
                os.unlink(entry.path)
                removed.append(Path(entry.path))
        except FileNotFoundError:  # gone meanwhile
            pass
        finally:
            os.close(fd)
    return removed


_RENAME_EXCHANGE = 2
_AT_FDCWD = -100


def exchange_paths(a: Path, b: Path) -> bool:
    """Atomically swap two paths (Linux renameat2 RENAME_EXCHANGE; a folder output swapped in
    with no instant where it is missing); False where the system or file system lacks it (or
    SLAMRELOC_NO_RENAME_EXCHANGE is set: the two-rename fallback, tested)."""
    if os.environ.get("SLAMRELOC_NO_RENAME_EXCHANGE"):
        return False
    import ctypes

    try:
        fn = ctypes.CDLL(None, use_errno=True).renameat2
    except (OSError, AttributeError):
        return False
    fn.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    if fn(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE) == 0:
        return True
    err = ctypes.get_errno()
    if err in (errno.ENOSYS, errno.EINVAL, errno.EOPNOTSUPP, errno.ENOTSUP):
        return False
    raise OSError(err, os.strerror(err), str(b))


def write_json(path: str | Path, data: dict) -> None:
    """Write `data` as indented JSON, atomically (strict JSON: a NaN or infinity is an error,
    never a `NaN` token other readers refuse)."""
    with atomic_file(path) as tmp:
        tmp.write_text(json.dumps(data, indent=2, allow_nan=False))
