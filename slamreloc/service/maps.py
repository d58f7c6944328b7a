"""The maps a server answers from: each loaded once, named, and swapped atomically on reload.

A `ServedMap` is immutable: a reload builds a new one beside the old and replaces the registry's
entry in one assignment, so a request that holds the old one finishes on it and the next request
gets the new one. Map writers (`slamreloc map`, `pseudo-label`) replace a map folder by an atomic
rename (`slamreloc.map.write`); the registry sees that as a new folder inode or a new metadata
file, and `watch` reloads it without a restart.
"""

from __future__ import annotations

import hashlib
import json
import queue
import threading
import time
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path

from slamreloc.errors import InputError
from slamreloc.localize.localizer import RegressorLocalizer
from slamreloc.map.format import DATABASE, META
from slamreloc.proto import relocalizer_pb2 as pb
from slamreloc.proto.messages import ServiceError
from slamreloc.map.scene_map import SceneMap


def folder_stamp(path: Path) -> tuple[int, int, int]:
    """What changes when a map folder is replaced or rewritten: (folder inode, metadata file
    mtime in ns, its size); zeros while the folder is missing (mid-swap)."""
    try:
        meta = (path / META).stat()
        return path.stat().st_ino, meta.st_mtime_ns, meta.st_size
    except OSError:
        return 0, 0, 0


@dataclass(frozen=True)
class ServedMap:
    name: str
    path: Path
    scene_map: SceneMap
    version: str  # sha256 of the map's metadata (which holds its files' digests), 12 hex
    stamp: tuple[int, int, int]
    loaded_at: float  # Unix seconds
    _pool: queue.SimpleQueue = field(default_factory=queue.SimpleQueue, repr=False)

    @staticmethod
    def load(name: str, path: Path) -> ServedMap:
        """Read and check the map (and its surface, used by depth refinement); InputError for a
        defect. A folder replaced while it is read fails its digests: read again, twice."""
        for attempt in range(3):
            stamp = folder_stamp(path)
            try:
                scene_map = SceneMap.load(path)
                _ = scene_map.surface
            except InputError:
                if attempt == 2 or folder_stamp(path) == stamp:
                    raise
                continue
            digest = hashlib.sha256(json.dumps(scene_map.meta, sort_keys=True).encode())
            return ServedMap(name, path, scene_map, digest.hexdigest()[:12], stamp, time.time())
        raise AssertionError("unreachable")

    @contextmanager
    def localizer(self) -> Iterator[RegressorLocalizer]:
        """A localizer of this map for the calling thread's request (one per concurrent
        request: the model is shared, the feature extractor is not)."""
        try:
            loc = self._pool.get_nowait()
        except queue.Empty:
            loc = RegressorLocalizer(self.scene_map)
        try:
            yield loc
        finally:
            self._pool.put(loc)

    def info(self) -> pb.MapInfo:
        m = self.scene_map
        db = m.root / DATABASE
        return pb.MapInfo(
            name=self.name, path=str(self.path), version=self.version,
            feature=m.info.feature_name, camera=m.camera.colmap_string(),
            metric=m.info.metric, num_points=m.info.n_labelled,
            size_bytes=m.size_bytes() + (db.stat().st_size if db.is_file() else 0),
            loaded_at=self.loaded_at, has_surface=m.surface is not None)


class MapRegistry:
    """name -> ServedMap. `get` never blocks on a reload."""

    def __init__(self, maps: dict[str, Path]):
        self._maps = {name: ServedMap.load(name, Path(path)) for name, path in maps.items()}
        self._reload_lock = threading.Lock()
        self._stop = threading.Event()

    @property
    def names(self) -> list[str]:
        return list(self._maps)

    def get(self, name: str) -> ServedMap:
        """The map named `name`; "" names the only map of a server with one."""
        maps = self._maps
        if not name and len(maps) == 1:
            return next(iter(maps.values()))
        if name not in maps:
            known = ", ".join(sorted(maps))
            raise ServiceError(pb.UNKNOWN_MAP, f"no map named {name!r} (served: {known})"
                               if name else f"name a map (served: {known})")
        return maps[name]

    def all(self) -> list[ServedMap]:
        return list(self._maps.values())

    def reload(self, name: str, force: bool = True) -> tuple[ServedMap, bool]:
        """Load the map's folder again and swap it in; (the map now served, whether its content
        changed). force=False: only when the folder's stamp changed."""
        with self._reload_lock:
            old = self.get(name)
            if not force and folder_stamp(old.path) in (old.stamp, (0, 0, 0)):
                return old, False
            try:
                new = ServedMap.load(old.name, old.path)
            except InputError as err:
                raise ServiceError(pb.INTERNAL, f"map {old.name!r} not reloaded, still serving "
                                   f"version {old.version}: {err}") from None
            if new.version == old.version:
                new = replace(old, stamp=new.stamp)  # same content: keep the loaded map
            self._maps = {**self._maps, old.name: new}  # one assignment: readers see old or new
            return new, new.version != old.version

    def watch(self, interval_s: float, on_reload=None) -> threading.Thread:
        """Reload any map whose folder was replaced, checking every `interval_s` seconds;
        `on_reload(ServedMap)` after each swap. Stops with `close`."""

        def run():
            while not self._stop.wait(interval_s):
                for name in self.names:
                    try:
                        served, changed = self.reload(name, force=False)
                    except ServiceError as err:
                        warnings.warn(err.message, stacklevel=1)
                        continue
                    if changed and on_reload is not None:
                        on_reload(served)

        thread = threading.Thread(target=run, name="map-watch", daemon=True)
        thread.start()
        return thread

    def close(self) -> None:
        self._stop.set()
