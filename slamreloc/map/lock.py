"""A map's write lock and what a killed map writer leaves beside it (`MAP_DEBRIS`), on the
folder lock every folder output shares (`slamreloc.io.folder_lock`). `build_map` and
`update_map` take it at their start; a map's readers clean a killed writer's leftovers
(`clean_leftovers`), and a server those of its learned maps' folder (`clean_maps_folder`).
"""

from __future__ import annotations

import os
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from slamreloc.errors import InputError
from slamreloc.io.folder_lock import Debris, folder_write_lock, holds_only, leftovers
from slamreloc.io.outputs import writer_pid
from slamreloc.map.format import is_map, is_map_file


def only_map_files(folder: Path) -> bool:
    """Whether `folder` holds nothing but regular files a map writer writes."""
    return holds_only(folder, is_map_file)


# a save cut short; a map moved aside (only its files: removed; with a user's file: put back
# where the map is missing, else kept)
MAP_DEBRIS = Debris(new=only_map_files, old=lambda f: is_map(f) and only_map_files(f),
                    put_back=is_map)


@contextmanager
def map_write_lock(out: str | Path) -> Iterator[None]:
    """Hold the exclusive write lock of the map folder `out` (re-entrant within a thread;
    `folder_write_lock`); a second process gets InputError at once. On entry a killed
    writer's leftovers are cleaned up, and a map it had moved aside is put back."""
    with folder_write_lock(out, "this map", MAP_DEBRIS):
        yield


def clean_leftovers(root: Path, wait_s: float = 10.0) -> None:
    """For a map's readers: if a killed writer left debris beside `root`, clean it (best
    effort)."""
    if not leftovers(root, MAP_DEBRIS):
        return
    deadline = time.monotonic() + wait_s
    while True:
        try:
            with map_write_lock(root):
                return
        except InputError:  # a live writer: it cleans up itself; wait if the map is moved
            if root.exists() or time.monotonic() > deadline:
                return
            time.sleep(0.05)
        except OSError:  # read-only location: nothing to do
            return


def _debris_name(entry: str) -> str | None:
    """The map NAME a killed writer's leftover `entry` belongs to (`.NAME.lock`,
    `.NAME.tmp-PID`, `.NAME.old-PID`), or None."""
    if not entry.startswith("."):
        return None
    if entry.endswith(".lock"):
        name = entry[1:-len(".lock")]
    else:
        cut = max(entry.rfind(".tmp-"), entry.rfind(".old-"))
        if cut <= 1 or writer_pid(entry, entry[:cut + 5]) is None:
            return None
        name = entry[1:cut]
    return name if name not in ("", ".", "..") else None


def clean_maps_folder(folder: Path) -> list[str]:
    """Clean what killed map writers left in `folder`, a folder of maps (a server's learned
    maps, after the server was killed while saving one): for each NAME such leftovers name,
    its write lock is taken and released, which removes a dead writer's lock file and
    unfinished save and puts back a map it had moved aside. A NAME a live writer holds, or
    whose lock file is not a writer's, is left as it is. Returns the NAMEs cleaned."""
    try:
        entries = [entry.name for entry in os.scandir(folder)]
    except OSError:  # cannot be listed: nothing to clean
        return []
    cleaned = []
    for name in sorted({n for n in map(_debris_name, entries) if n is not None}):
        try:
            with map_write_lock(folder / name):
                pass
        except (InputError, OSError):  # a live writer's, or not a writer's: left alone
            continue
        cleaned.append(name)
    return cleaned
