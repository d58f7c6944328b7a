"""Crash-safe writing of a map folder (the format is format.py's, the metadata's meta.py's).

The new map is written into `.NAME.tmp-PID` beside MAP and swapped in with one atomic
`renameat2(RENAME_EXCHANGE)` (two renames where the file system lacks it; a crash between them
is rolled back at the next start), all under the map's write lock (lock.py).
"""

from __future__ import annotations

import errno
import json
import os
import sys
from collections.abc import Callable
from contextlib import ExitStack
from pathlib import Path

import numpy as np

from slamreloc.errors import InputError
from slamreloc.io.outputs import (commit_output, exchange_paths, naming_output, record_written,
                                  still_as_checked, temp_dir_path, what_is_there)
from slamreloc.map.format import (DATABASE, FORMAT_VERSION, MAP_FILES, META, WEIGHTS, is_map,
                                  is_map_file, sha256_file)
from slamreloc.io.folder_lock import fsync_dir
from slamreloc.map.lock import map_write_lock
from slamreloc.map.meta import MapMeta
from slamreloc.map.weights import weight_arrays
from slamreloc.regressor.model import SceneCoordinateRegressor
from slamreloc.map.scene_map import MapDatabase, SceneMap


def check_map_target(out: Path) -> None:
    """Raise unless `out` is absent, an empty folder, or a slamreloc map holding nothing but
    a map's files (to be replaced whole: anything else in it would go with it). A symbolic
    link is refused whatever it points to: the writer replaces the link, and never writes or
    deletes through it (checked again at the swap: `_swap_in`)."""
    out = Path(out)
    if out.is_symlink():
        raise InputError(f"{out}: is a symbolic link (to {os.readlink(out)[:200]}), not a "
                         "folder; a map writer replaces a folder and never writes through a "
                         "link: give the map's own folder")
    if out.exists() and (not out.is_dir() or (any(out.iterdir()) and not is_map(out))):
        raise InputError(f"{out}: exists and is not a slamreloc map; refusing to overwrite it")
    if out.is_dir():
        entries = sorted((e for e in os.scandir(out) if not is_map_file(e)),
                         key=lambda e: e.name)
        links = [e.name for e in entries if e.is_symlink() and e.name in MAP_FILES]
        odd = [e.name for e in entries if e.name in MAP_FILES and e.name not in links]
        foreign = [e.name for e in entries if e.name not in MAP_FILES]
        if odd and is_map(out):  # a map file's name on a named pipe, a folder, a device...
            raise InputError(f"{out}: its {odd[0]!r} is {what_is_there(out / odd[0])}, not a "
                             "map writer's file; refusing to replace it (give the map's own "
                             "folder, or move it out)")
        if links and is_map(out):  # the map's own names, as links: a writer replaces files
            raise InputError(f"{out}: its {', '.join(map(repr, links[:3]))}"
                             f"{' ...' if len(links) > 3 else ''} "
                             f"{'is a symbolic link' if len(links) == 1 else 'are symbolic links'}"
                             ", not a map writer's files; refusing to replace it (give the "
                             "map's own folder, or copy the files in)")
        if foreign and is_map(out):
            raise InputError(f"{out}: also holds {', '.join(map(repr, foreign[:3]))}"
                             f"{' ...' if len(foreign) > 3 else ''}, which is not a map's; "
                             "refusing to replace it (move those out first)")


def _clear_own_path(path: Path, out: Path) -> None:
    """Make way for this writer's temporary `path` beside `out` (named with this process's
    id): a folder this process made there and could not remove (`_MADE`) is removed now;
    anything else there is refused, never deleted - a user's, or a killed writer's whose
    process id this process has again (as in a container), which the message asks to move."""
    if not os.path.lexists(path):
        return
    if path not in _MADE or path.is_symlink() or not path.is_dir():
        raise InputError(f"{path}: in the way of writing {out.name}, and not made by this "
                         "process (a user's, or a killed writer's with this process id); "
                         "refusing to delete it (move it)")
    _remove_old_copy(path, out)


def _remove_old_copy(old: Path, out: Path) -> None:
    """Remove `old`, a folder this writer made or moved aside (the temporary folder, or the
    map `out` held before the swap): its map files are deleted; anything else in it (a file
    someone wrote into the map's folder while the new map was being written) is moved into
    `out`, where it was put, never deleted. `old` is opened without following links, and its
    entries are reached through that handle: a link or a file put in its place is left as it
    is, and nothing it points to is touched. A folder that cannot be removed is remembered
    (`_MADE`), so that this process may remove it at its next write, and said on stderr."""
    _MADE.add(old)
    try:
        fd = os.open(old, os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW)
    except FileNotFoundError:
        _MADE.discard(old)
        return
    except OSError as err:
        _MADE.discard(old)  # a link or a file: not this writer's to remove, ever
        print(f"warning: {old}: left as it is ({err.strerror or err}): it is not the folder "
              "this writer made; nothing it points to was touched", file=sys.stderr)
        return
    try:
        with os.scandir(fd) as entries:
            for entry in entries:
                if is_map_file(entry):
                    os.unlink(entry.name, dir_fd=fd)
                elif out.is_dir() and not os.path.lexists(out / entry.name):
                    os.rename(entry.name, out / entry.name, src_dir_fd=fd)
                    print(f"note: {out / entry.name}: written into {out.name} while it was "
                          "being replaced; kept", file=sys.stderr)
                else:
                    raise OSError(errno.EEXIST, "a file that is not the map's is in the way",
                                  str(old / entry.name))
        old.rmdir()
        _MADE.discard(old)
    except FileNotFoundError:
        _MADE.discard(old)
    except OSError as err:
        print(f"warning: {old}: not removed ({err.strerror or err}); this process removes "
              "it at its next write of the map", file=sys.stderr)
    finally:
        os.close(fd)


# temporary and old folders this process made beside maps and has not removed yet (a removal
# that failed: `_remove_old_copy`)
_MADE: set[Path] = set()


def _crash_point(name: str) -> None:
    """Test hook: SLAMRELOC_TEST_CRASH_AT=name kills this process here (as kill -9 would)."""
    if os.environ.get("SLAMRELOC_TEST_CRASH_AT") == name:
        os.kill(os.getpid(), 9)


def _write_npz(path: Path, arrays: dict[str, np.ndarray]) -> str:
    with open(path, "wb") as f:
        np.savez(f, **arrays)
        f.flush()
        os.fsync(f.fileno())
    return sha256_file(path)


def _swap_in(tmp: Path, out: Path) -> Callable[[], None]:
    """Make the complete map `tmp` appear at `out`; `out`'s old contents end at `tmp` (or the
    .old sibling, `temp_dir_path(out, "old")`) to be removed once the write is done. At every
    instant `out` is a complete map, except in the two-rename fallback, whose gap `_recover`
    repairs. Returns how to put the old map back (`commit_output`'s undo)."""
    old = temp_dir_path(out, "old")
    _check_still_folder(out)

    def new_out() -> None:  # there was no map: the new one goes back to its temporary
        os.replace(out, tmp)

    def exchange_back() -> None:
        exchange_paths(tmp, out)

    def old_back() -> None:
        os.replace(out, tmp)
        os.replace(old, out)

    if not out.exists():
        os.replace(tmp, out)
        undo = new_out
    elif exchange_paths(tmp, out):
        undo = exchange_back
        if tmp.is_symlink() or not tmp.is_dir():  # replaced in the instant since the check
            exchange_back()
            _check_still_folder(out)
            raise InputError(f"{out}: replaced while the map was written; not written")
    else:
        _clear_own_path(old, out)
        os.replace(out, old)
        _MADE.add(old)  # removed when the write is done (`save_map`)
        _crash_point("between-renames")
        os.replace(tmp, out)
        undo = old_back
    fsync_dir(out.parent)
    record_written(out)
    return undo


def _check_still_folder(out: Path) -> None:
    """Raise where `out` has become something a map writer must not replace since its checks
    (a symbolic link, a file; or anything else than `check_outputs` saw, its folder included:
    `still_as_checked`): the new map is then discarded, what is at `out` kept."""
    still_as_checked(out)
    if out.is_symlink() or os.path.lexists(out) and not out.is_dir():
        raise InputError(f"{out}: became {what_is_there(out)} while the map was written; not "
                         "written (what is there is kept, the new map discarded)")


def save_map(out: str | Path, meta: MapMeta, model: SceneCoordinateRegressor, db: MapDatabase,
             extra: dict[str, dict[str, np.ndarray]] | None = None) -> Path:
    """Write a map atomically: into a temporary sibling folder, then swap it in for `out`
    (inside `outputs_together`, with the block's other outputs; the write lock is held until
    then). `meta` is written stamped (`MapMeta.stamped`) with today's format, this version,
    the files' checksums and `db`'s frame names and pictures. `extra`: more array files
    (name -> arrays, no pickle) written into the map with it.

    Refuses to replace an existing non-empty folder that is not a slamreloc map, and fails at
    once if another process is writing `out`."""
    out = Path(out)
    with ExitStack() as held:  # the write lock, and what to remove, until the swap is done
        held.enter_context(map_write_lock(out))
        with naming_output(out):
            check_map_target(out)
            tmp = temp_dir_path(out)
            _clear_own_path(tmp, out)
            tmp.mkdir(parents=True)
            _MADE.add(tmp)
        held.callback(_remove_old_copy, tmp, out)  # the old map after the swap, or the unused new
        old = temp_dir_path(out, "old")  # the old map in the two-rename fallback
        held.callback(lambda: old in _MADE and _remove_old_copy(old, out))
        with naming_output(out):
            _write_map_files(tmp, out, meta, model, db, extra)
        release = held.pop_all()  # from here, the commit's to close

    def swap() -> Callable[[], None]:
        with naming_output(out):
            _crash_point("before-swap")
            undo = _swap_in(tmp, out)
            _crash_point("after-swap")
        return undo

    commit_output(swap, release.close, folder=True)
    return out


def _write_map_files(tmp: Path, out: Path, meta: MapMeta, model: SceneCoordinateRegressor,
                     db: MapDatabase, extra: dict[str, dict[str, np.ndarray]] | None) -> None:
    """Write the map's files into its temporary folder `tmp` (synced), the metadata last,
    after checking it as readers of `out` will."""
    files = {
        WEIGHTS: _write_npz(tmp / WEIGHTS, weight_arrays(model)),
        DATABASE: _write_npz(tmp / DATABASE, {
            "descriptors": db.descriptors.astype(np.float16),
            "points": db.points.astype(np.float32),
            "keypoints": db.keypoints.astype(np.float32),
            "frame_index": db.frame_index.astype(np.int32),
            "world_from_cam": np.asarray(db.world_from_cam, np.float64)}),
    }
    for name, arrays in (extra or {}).items():
        files[name] = _write_npz(tmp / name, arrays)
    _crash_point("files-written")
    known = len(db.frame_pictures) == len(db.frame_names) and any(db.frame_pictures)
    doc = meta.stamped(files, db.frame_names, db.frame_pictures if known else None).to_json()
    # what readers will check, checked before the swap: a document they would refuse never
    # replaces a map that loads
    try:
        MapMeta.from_json(json.loads(json.dumps(doc)), out / META)
    except InputError as err:
        raise InputError(f"{out}: not written (what was there is kept): its metadata would "
                         f"not load: {err}") from None
    with open(tmp / META, "w") as f:
        f.write(json.dumps(doc, indent=1))
        f.flush()
        os.fsync(f.fileno())
    fsync_dir(tmp)


def migrate_map(path: str | Path) -> Path:
    """Rewrite an older-format map in place in the current format (atomically)."""
    old = SceneMap.load(path)
    if old.format_version == FORMAT_VERSION:
        return old.root
    return save_map(old.root, old.info, old.regressor, old.database)
