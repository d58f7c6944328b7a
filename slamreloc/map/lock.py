"""A map's write lock and what a killed map writer leaves beside it (`MAP_DEBRIS`), on the
folder lock every folder output shares (`slamreloc.io.folder_lock`). `build_map` and
`update_map` take it at their start; a map's readers clean a killed writer's leftovers
(`clean_leftovers`).
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from slamreloc.errors import InputError
from slamreloc.io.folder_lock import Debris, folder_write_lock, holds_only, leftovers
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
