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
from functools import cached_property
from pathlib import Path

from slamreloc.errors import InputError
from slamreloc.io.fileio import (CANCEL_READS, ReadCancelled, disk_identities, relation,
                                 relation_on_disk, resolved)
from slamreloc.io.outputs import is_writers_name
from slamreloc.localize.localizer import RegressorLocalizer
from slamreloc.map.format import DATABASE, META, PROVENANCE
from slamreloc.proto import relocalizer_pb2 as pb
from slamreloc.proto.messages import ServiceError, map_name_problem, quoted
from slamreloc.map.scene_map import SceneMap


def folder_stamp(path: Path) -> tuple[int, int, int]:
    """What changes when a map folder is replaced or rewritten: (folder inode, metadata file
    mtime in ns, its size); zeros while the folder is missing (mid-swap)."""
    try:
        meta = (path / META).stat()
        return path.stat().st_ino, meta.st_mtime_ns, meta.st_size
    except OSError:
        return 0, 0, 0


def _same_folder(a: Path, b: Path) -> bool:
    try:
        return Path(a).resolve() == Path(b).resolve()
    except (OSError, RuntimeError):
        return False


def _folder_now(path: Path) -> tuple[bool, Path]:
    """(whether `path` is a symbolic link, the folder it resolves to), now."""
    return Path(path).is_symlink(), resolved(path)


class LoadCancelled(ReadCancelled):
    """A map load given up because the server stops (between its files, or inside one:
    CANCEL_READS, which `_Load` sets on its thread, is checked by every checksum read)."""


@dataclass(frozen=True)
class ServedMap:
    name: str
    path: Path
    scene_map: SceneMap
    version: str  # sha256 of the metadata and of every file's contents as read, 12 hex
    stamp: tuple[int, int, int]
    loaded_at: float  # Unix seconds
    folder: Path | None = None  # the folder `path` resolved to when it was loaded
    linked: bool = False  # whether `path` was a symbolic link when it was loaded
    _pool: queue.SimpleQueue = field(default_factory=queue.SimpleQueue, repr=False)

    @staticmethod
    def load(name: str, path: Path) -> ServedMap:
        """Read and check every file the map is served from - the regressor, the training
        database, the surface (depth refinement), the provenance - each against its checksum
        as it is read; InputError for a defect, including a file the metadata lists that is
        missing (a training database too: a served map is served as written). The version is
        computed from the contents actually read, so a folder replaced by one with the same
        metadata but other files has another version (or fails its checks). A folder replaced
        while it is read fails its digests: read again, twice. The registry's stop event set
        (`CANCEL_READS`, the server stopping): `LoadCancelled` between files, and within a
        file's checksum read."""
        cancelled = CANCEL_READS.get()

        def step() -> None:
            if cancelled is not None and cancelled.is_set():
                raise LoadCancelled(f"map {quoted(name)}: load cancelled (the server stops)")

        for attempt in range(3):
            step()
            stamp = folder_stamp(path)
            linked, folder = _folder_now(path)
            try:
                scene_map = SceneMap.load(path)
                step()
                if scene_map.has_database or scene_map.lists_database:
                    _ = scene_map.database
                step()
                _ = scene_map.surface
                _ = scene_map.info.metric  # what info() answers: refused here, not per call
                # the recorded inputs a save must keep clear of: checked on every load, as
                # at start-up with `--learned-maps`
                _ = scene_map.info.recorded_inputs()
                if scene_map.provenance_unverified:  # documented: read without a checksum
                    warnings.warn(f"map {quoted(name)}: {path / PROVENANCE} is not listed in "
                                  f"{META}: served without checking its checksum (rewrite the "
                                  "map to list it)", stacklevel=1)
                _ = scene_map.provenance
            except ReadCancelled:  # inside a file's checksum read
                raise LoadCancelled(f"map {quoted(name)}: load cancelled (the server "
                                    "stops)") from None
            except InputError:
                if attempt == 2 or folder_stamp(path) == stamp:
                    raise
                continue
            served = ServedMap(name, path, scene_map, content_version(scene_map), stamp,
                               time.time(), folder, linked)
            _ = served.size_bytes  # measured now, as loaded
            return served
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

    @cached_property
    def size_bytes(self) -> int:
        """The weights', metadata's and database's bytes when loaded (never a stat of the
        folder at answer time: it may be mid-swap, or hold something else by then)."""
        try:
            m = self.scene_map
            db = m.root / DATABASE
            return m.size_bytes() + (db.stat().st_size if db.is_file() else 0)
        except OSError:
            return 0

    def info(self) -> pb.MapInfo:
        m = self.scene_map
        return pb.MapInfo(
            name=self.name, path=str(self.path), version=self.version,
            feature=m.info.feature_name, camera=m.camera.colmap_string(),
            metric=m.info.metric,
            num_points=len(m.database.points) if m.has_database else m.info.n_labelled,
            size_bytes=self.size_bytes,
            loaded_at=self.loaded_at, has_surface=m.surface is not None)


def content_version(scene_map: SceneMap) -> str:
    """12 hex digits of a SHA-256 over the map's metadata and the digests of its files'
    contents as they were read."""
    h = hashlib.sha256(json.dumps(scene_map.meta, sort_keys=True).encode())
    for name, digest in sorted(scene_map.digests.items()):
        h.update(f"\n{name}:{digest}".encode())
    return h.hexdigest()[:12]


class _Load:
    """One load of a map folder on a thread of its own; `done` is set when it ends. The thread
    is not a daemon: the interpreter never exits under it (torch torn down under a running
    load aborts the process); `MapRegistry.close` cancels it between files and waits."""

    def __init__(self, name: str, path: Path, cancelled: threading.Event):
        self.done = threading.Event()
        self.waited = True  # a caller waits for it (False once it gave up: the next may wait)
        self.started = time.monotonic()
        self.result: ServedMap | None = None
        self.error: BaseException | None = None
        self.thread = threading.Thread(target=self._run, args=(name, path, cancelled),
                                       name=f"map-load-{name[:40]}")
        self.thread.start()

    def _run(self, name: str, path: Path, cancelled: threading.Event) -> None:
        CANCEL_READS.set(cancelled)  # this thread's own context
        try:
            self.result = ServedMap.load(name, path)
        except BaseException as err:  # noqa: BLE001 - handed to the waiting request
            self.error = err
        finally:
            self.done.set()


def check_served_folders(maps: dict[str, Path]) -> None:
    """InputError, before any map is read, unless each folder to serve is one of its own:
    not named as a writer's temporary (`.NAME.tmp-PID`, `.NAME.old-PID`: a map's readers and
    writers remove such a folder beside NAME, or put it back as NAME, as a killed writer's),
    and apart from every other served map's folder (not the same folder under another path,
    a link or a bind mount, not inside it, not holding it: the reload's rule, as two names
    would serve one folder and a session could save neither)."""
    folders: dict[str, tuple[Path, list]] = {}  # name -> (folder, its disk identities)
    for name, path in maps.items():
        path = Path(path)
        folder = resolved(path)  # a link's target too
        if is_writers_name(path.name) or is_writers_name(folder.name):
            raise InputError(f"{path}: the map {quoted(name)} is named as a writer's temporary "
                             "(.NAME.tmp-PID, .NAME.old-PID), which the next read or write of "
                             "NAME removes or puts back as NAME; rename it to serve it")
        ids = disk_identities(folder)  # once per folder: many maps are compared pairwise
        for other, (other_folder, other_ids) in folders.items():
            how = relation_on_disk(folder, other_folder, ids, other_ids)
            if how:
                raise InputError(f"{path}: the folder of the map {quoted(name)} {how} the "
                                 f"folder of the map {quoted(other)}; serve a folder under one "
                                 "name (a session could save under neither)")
        folders[name] = (folder, ids)


class MapRegistry:
    """name -> ServedMap. `get` never blocks on a reload; a reload never blocks for longer
    than `load_timeout_s` (then it is refused, OVERLOADED, and the map already loaded keeps
    serving); at most one load of each map runs at a time, one caller waits for it, and a
    reload asked for meanwhile is refused at once (OVERLOADED): a caller never queues behind
    another's."""

    def __init__(self, maps: dict[str, Path], load_timeout_s: float = 300.0):
        check_served_folders(maps)  # before any load: a map's reader cleans beside it
        self._maps = {name: ServedMap.load(name, Path(path)) for name, path in maps.items()}
        self.load_timeout_s = load_timeout_s
        self._reload_lock = threading.Lock()  # held only to look up and to swap, never to load
        self._loading: dict[str, _Load] = {}
        self._registering: set[str] = set()  # maps a save is putting in: no other load starts
        self._stop = threading.Event()
        self._watcher: threading.Thread | None = None

    @property
    def names(self) -> list[str]:
        return list(self._maps)

    def get(self, name: str) -> ServedMap:
        """The map named `name`; "" names the only map of a server with one."""
        maps = self._maps
        if not name and len(maps) == 1:
            return next(iter(maps.values()))
        if name not in maps:
            known = ", ".join(quoted(n) for n in sorted(maps))
            problem = map_name_problem(name) if name else None  # the clients' rule, said
            raise ServiceError(pb.UNKNOWN_MAP, f"no map named {quoted(name)}"
                               + (f": the name {problem}" if problem else "")
                               + f" (served: {known})" if name else
                               f"name a map (served: {known})")
        return maps[name]

    def all(self) -> list[ServedMap]:
        return list(self._maps.values())

    def loading(self, name: str) -> bool:
        """Whether a load of the map `name` is running."""
        load = self._loading.get(name)
        return load is not None and not load.done.is_set()

    def reload(self, name: str, force: bool = True) -> tuple[ServedMap, bool]:
        """Load the map's folder again and swap it in; (the map now served, whether its content
        changed since this call began). force=False: only when the folder's stamp changed.
        ServiceError OVERLOADED at once while another caller waits for a load of the map (at
        most one runs, and one caller waits for it), while a session's save of it is being put
        in (`register`), and when the load outlasts `load_timeout_s` (it is left to finish on
        its own: the next reload waits for it and takes its result if it still runs then);
        INTERNAL for a folder that fails its checks. The map already loaded serves meanwhile,
        and on any refusal."""
        return self._reload(name, force, registering=False)

    def _reload(self, name: str, force: bool, registering: bool) -> tuple[ServedMap, bool]:
        with self._reload_lock:
            if self._stop.is_set():
                raise ServiceError(pb.OVERLOADED, "the server is stopping")
            old = self.get(name)
            if old.name in self._registering and not registering:
                raise ServiceError(pb.OVERLOADED, f"map {quoted(old.name)} is being replaced "
                                   "by a session's save; still serving version "
                                   f"{old.version}: try again when it is done")
            load = self._loading.get(old.name)
            if load is not None and not load.done.is_set():
                if load.waited:  # one caller waits for a map's load, never more
                    raise ServiceError(pb.OVERLOADED, f"map {quoted(old.name)} is still "
                                       f"loading (for {time.monotonic() - load.started:.1f} "
                                       f"s); still serving version {old.version}: try again "
                                       "when it is done")
                load.waited = True  # its caller gave up: this one takes its result
            elif load is not None:  # finished with no one waiting: stale
                del self._loading[old.name]
                load = None
            if load is None:
                if not force and folder_stamp(old.path) in (old.stamp, (0, 0, 0)):
                    return old, False
                self._check_folder(old.name, *_folder_now(old.path))
                load = self._loading[old.name] = _Load(old.name, old.path, self._stop)
        if not load.done.wait(self.load_timeout_s):
            with self._reload_lock:
                load.waited = False
            raise ServiceError(pb.OVERLOADED, f"map {quoted(old.name)} not reloaded: reading "
                               f"its folder takes over {self.load_timeout_s:g} s; still serving "
                               f"version {old.version}")
        with self._reload_lock:
            if self._loading.get(old.name) is load:
                del self._loading[old.name]
                if load.error is None:  # the folder as the load found it, and as it is now
                    new = load.result
                    self._check_folder(old.name, new.linked, new.folder)
                    self._check_folder(old.name, *_folder_now(old.path))
                    current = self._maps.get(old.name, old)
                    if new.version == current.version:  # same content: keep the loaded map
                        new = replace(current, stamp=new.stamp, folder=new.folder,
                                      linked=new.linked)
                    self._maps = {**self._maps, old.name: new}  # one assignment: readers see
                    # the old map or the new one
        if isinstance(load.error, ReadCancelled):
            raise ServiceError(pb.OVERLOADED, str(load.error)) from None
        if isinstance(load.error, InputError):
            raise ServiceError(pb.INTERNAL, f"map {quoted(old.name)} not reloaded, still "
                               f"serving version {self.get(old.name).version}: "
                               f"{load.error}") from None
        if load.error is not None:
            raise load.error
        now = self.get(old.name)
        return now, now.version != old.version

    def _check_folder(self, name: str, linked: bool, folder: Path) -> None:
        """ServiceError FAILED_PRECONDITION (the map served keeps serving) unless the map `name`
        may be reloaded from its path as it is now (`linked`: a symbolic link; `folder`: where
        it resolves): a path that was no link when the map was loaded has not become one (a
        map folder replaced by a link to another), and a folder that resolves elsewhere than
        when it was loaded is not, does not hold and does not lie inside the folder of a map
        served under another name (two names would serve one folder, and a session could
        save neither). A path served as a link from the start may be pointed at another map
        folder of its own (a `current` link switched to a new version)."""
        current = self._maps[name]
        problem = None
        if linked and not current.linked:
            problem = "its folder was replaced by a symbolic link"
        elif current.folder is None or folder != current.folder:
            for m in self._maps.values():
                how = None if m.name == name else relation(folder, m.folder or resolved(m.path))
                if how:
                    problem = (f"its folder now {how} the folder of the map "
                               f"{quoted(m.name)} this server serves")
                    break
        if problem is not None:
            raise ServiceError(pb.FAILED_PRECONDITION, f"map {quoted(name)} not reloaded, still "
                               f"serving version {current.version}: {problem}; a map is "
                               "reloaded only from a folder of its own (restore it)")

    def register(self, name: str, path: Path) -> ServedMap:
        """Serve the map folder `path` as `name` (a map a session saved): added where `name` is
        not served yet, loaded again and swapped in where it is served from `path` already
        (as `reload`: requests in flight finish on the old one). ServiceError
        FAILED_PRECONDITION where `name` is served from another folder; INTERNAL for a folder
        that fails its checks; OVERLOADED while the server stops, or when another load of the
        map (a ReloadMap's, the watch's) outlasts `load_timeout_s`. Meanwhile no other load of
        `name` starts (a ReloadMap loop cannot hold the save off): one running is waited for,
        never taken (it may have read the folder before the save), then the map is loaded."""
        path = Path(path)
        with self._reload_lock:
            self._registering.add(name)
        try:
            return self._register(name, path)
        finally:
            with self._reload_lock:
                self._registering.discard(name)

    def _register(self, name: str, path: Path) -> ServedMap:
        until = time.monotonic() + self.load_timeout_s
        while True:
            with self._reload_lock:
                if self._stop.is_set():
                    raise ServiceError(pb.OVERLOADED, "the server is stopping")
                current = self._maps.get(name)
                if current is not None and not _same_folder(current.path, path):
                    raise ServiceError(pb.FAILED_PRECONDITION, f"a map named {quoted(name)} is "
                                       f"already served from another folder")
            if current is None:
                try:
                    new = ServedMap.load(name, path)
                except InputError as err:
                    raise ServiceError(pb.INTERNAL, f"map {quoted(name)} saved but not "
                                       f"served: {err}") from None
                with self._reload_lock:
                    if name not in self._maps:  # (saves are serialised by the server)
                        self._maps = {**self._maps, name: new}
                        return new
                continue
            running = self._loading.get(name)
            if running is not None:  # begun before the save: waited for, never taken (a
                # finished load is stale to `_reload`, which loads the folder anew)
                running.done.wait(max(0.0, until - time.monotonic()))
            try:
                return self._reload(name, True, registering=True)[0]
            except ServiceError as err:  # another load still runs: wait for it
                if err.kind != pb.OVERLOADED or self._stop.is_set() \
                        or time.monotonic() > until:
                    raise
                time.sleep(0.05)

    def watch(self, interval_s: float, on_reload=None, on_failure=None) -> threading.Thread:
        """Reload any map whose folder was replaced, checking every `interval_s` seconds;
        `on_reload(ServedMap)` after each swap. Stops with `close`. A map that fails to load
        is reported once per version of its folder (`on_failure(message)`, else a warning
        that is shown every time, not once per text as Python's filter would), and retried
        when the folder changes; a map whose load (a ReloadMap's) is running is looked at
        again next time."""
        failed: dict[str, tuple[int, int, int]] = {}

        def report(message: str) -> None:
            if on_failure is not None:
                on_failure(message)
            else:  # no registry: Python's default filter would show a text only once
                warnings.warn_explicit(message, UserWarning, __file__, 0, registry=None)

        def run():
            while not self._stop.wait(interval_s):
                for name in self.names:
                    if self._stop.is_set():
                        return
                    try:
                        served = self.get(name)
                        stamp = folder_stamp(served.path)
                        if failed.get(name) == stamp or self.loading(name):
                            continue
                        served, changed = self.reload(name, force=False)
                    except ServiceError as err:
                        if err.kind == pb.OVERLOADED:  # a load or a save of it still runs:
                            continue  # looked at again next time (its refusal is a client's)
                        failed[name] = stamp
                        if not self._stop.is_set():
                            report(err.message)
                        continue
                    except Exception as err:  # noqa: BLE001 - the watch carries on
                        failed[name] = stamp
                        report(f"map {quoted(name)}: {type(err).__name__}: {err}")
                        continue
                    failed.pop(name, None)
                    if changed and on_reload is not None:
                        on_reload(served)

        thread = self._watcher = threading.Thread(target=run, name="map-watch", daemon=True)
        thread.start()
        return thread

    def close(self) -> None:
        """Stop the watch and every load: a load is cancelled between the files it reads and
        waited for (a file being read is finished first), so no load thread outlives this."""
        self._stop.set()
        with self._reload_lock:
            loads = list(self._loading.values())
        for load in loads:
            load.thread.join()
        if self._watcher is not None and self._watcher is not threading.current_thread():
            self._watcher.join()
