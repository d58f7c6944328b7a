"""The map: its regressor (what localization needs), the labelled training database, and what
else its folder holds (fused surface, provenance of an updated map's labels), each read on
first use, checked against the metadata and its checksum. The folder's format is format.py's,
its metadata's schema meta.py's; writing it is write.py's.

    scene_map = SceneMap.load(MAP)                    # checks the metadata, builds the regressor
    scene_map = SceneMap.load(MAP, regressor=False)   # the same checks, no model (the viewer)
    scene_map.info                                    # the metadata (MapMeta)
    scene_map.database, scene_map.surface, scene_map.provenance
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import BinaryIO

import numpy as np

from slamreloc.errors import InputError
from slamreloc.geometry import Rigid3
from slamreloc.io.fileio import file_identity, open_regular
from slamreloc.map.format import (
    DATABASE,
    DB_KEYS,
    META,
    PROVENANCE,
    SURFACE,
    WEIGHTS,
    ChecksumMismatch,
    check_database,
    check_digest,
    check_is_map,
    check_provenance,
    is_map,
    read_npz,
)
from slamreloc.map.lock import clean_leftovers
from slamreloc.map.meta import MapMeta
from slamreloc.map.weights import read_regressor
from slamreloc.regressor.model import SceneCoordinateRegressor
from slamreloc.map.surface import Surface
from slamreloc.types import Camera


def rows_by_frame(frame_index: np.ndarray, n_frames: int) -> list[np.ndarray]:
    """For each frame 0..n_frames-1, the indices of the rows whose `frame_index` is that
    frame, in row order."""
    order = np.argsort(frame_index, kind="stable")
    bounds = np.searchsorted(frame_index[order], np.arange(n_frames + 1))
    return [order[bounds[i]:bounds[i + 1]] for i in range(n_frames)]


@dataclass
class MapDatabase:
    descriptors: np.ndarray  # (M, D) float16, labelled training descriptors
    points: np.ndarray  # (M, 3) float32 world points, metres
    keypoints: np.ndarray  # (M, 2) float32 pixels
    frame_index: np.ndarray  # (M,) int32 into frame_names
    frame_names: list[str] = field(default_factory=list)
    world_from_cam: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4)))
    # each frame's picture (`io.images.picture_digest`; "" where not known), in the order of
    # `frame_names`; empty: none known (`MapMeta.frame_pictures`)
    frame_pictures: list[str] = field(default_factory=list)


@dataclass(frozen=True)
class MapProvenance:
    """Where each database row of an updated map came from (provenance.npz)."""

    source: np.ndarray  # (M,) int8: format.LABELLED, PSEUDO or NEW
    quality: np.ndarray  # (M,) float32 training weight in 0..1 (1 for labelled rows)


_LOAD_ATTEMPTS = 5  # a load that met a map swapped in meanwhile reads the new one whole


def _meta_identity(root: Path) -> tuple[int, ...] | None:
    """Which metadata file `root` holds now (`file_identity`): every save writes a new one,
    so a change means a map was saved over the folder."""
    return file_identity(root / META)


def _open_listed(root: Path, info: MapMeta) -> dict[str, BinaryIO]:
    """The files besides the weights that `info` lists, opened (those that open: a missing
    or special file is reported where it is read, by path)."""
    held = {}
    for name in (DATABASE, SURFACE, PROVENANCE):
        if name in (info.files or {}):
            try:
                held[name] = open_regular(root / name, "map file")
            except InputError:
                pass
    return held


@dataclass
class SceneMap:
    root: Path
    info: MapMeta  # slamreloc_map.json, checked
    regressor: SceneCoordinateRegressor | None  # None: loaded with regressor=False
    # file name -> SHA-256 of the bytes actually read (each file is hashed as it is parsed)
    digests: dict[str, str] = field(default_factory=dict, compare=False, repr=False)
    # the map's other listed files, opened at the load with its metadata and weights and read
    # on first use: a map saved over the folder meanwhile does not mix into this one
    held: dict[str, BinaryIO] = field(default_factory=dict, compare=False, repr=False)
    # the metadata file read (`_meta_identity`): another one there now means another map
    meta_identity: tuple[int, ...] | None = field(default=None, compare=False, repr=False)

    @staticmethod
    def is_map(path: Path) -> bool:
        return is_map(path)

    @staticmethod
    def load(path: str | Path, regressor: bool = True) -> SceneMap:
        """Read and check a map folder; any defect raises InputError naming the file.
        `regressor=False` checks the weights' checksum but builds no model (for readers of the
        database only)."""
        root = Path(path)
        clean_leftovers(root)
        for attempt in range(_LOAD_ATTEMPTS):
            check_is_map(root)  # says what is there instead: a file, a pipe, a link loop
            identity = _meta_identity(root)
            info = MapMeta.read(root)
            digests: dict[str, str] = {}
            last = attempt == _LOAD_ATTEMPTS - 1
            try:
                if regressor:
                    model = read_regressor(root, info, digests)
                else:
                    model = None
                    if info.format_version >= 2:
                        digests[WEIGHTS] = check_digest(root, WEIGHTS, info.files)
                held = _open_listed(root, info)
                if _meta_identity(root) != identity and not last:
                    for f in held.values():  # perhaps another map's, swapped in meanwhile
                        f.close()
                    continue
                return SceneMap(root, info, model, digests, held, identity)
            except ChecksumMismatch:
                # a writer swapped a new map in between the metadata and the weights: read
                # the new one whole; a damaged file (the metadata unchanged) is reported
                if _meta_identity(root) == identity or last:
                    raise
        raise AssertionError("unreachable")

    @property
    def meta(self) -> dict:
        """slamreloc_map.json as read (`info.to_json()`; `format_version` always set)."""
        return self.info.to_json()

    @cached_property
    def camera(self) -> Camera:
        """The training frames' camera."""
        return self.info.camera.to_camera()

    @property
    def format_version(self) -> int:
        return self.info.format_version

    @cached_property
    def database(self) -> MapDatabase:
        path = self.root / DATABASE
        if not path.exists() and not path.is_symlink():
            raise InputError(f"{path}: the map lists a training database (with its checksum) "
                             "but the file is missing" if self.lists_database
                             else f"{path}: map has no training database")
        expected = (self.info.files or {}).get(DATABASE) if self.format_version >= 2 else None
        if self.format_version >= 2 and expected is None:
            raise InputError(f"{path}: no checksum for it in {META}")
        arrays = self._read_npz(DATABASE, "training database", expected)
        names = None if self.info.frame_names is None else list(self.info.frame_names)
        check_database(arrays, path, self.info.regressor.to_config().in_dim, names)
        self.info.check_database_counts(len(arrays["points"]), len(arrays["world_from_cam"]),
                                        path)
        return MapDatabase(*(arrays[k] for k in DB_KEYS[:4]), names or [],
                           arrays["world_from_cam"], list(self.info.frame_pictures or ()))

    def _read_npz(self, name: str, what: str, expected: str | None) -> dict[str, np.ndarray]:
        """`read_npz` of the map's file `name`; a checksum mismatch because the folder now
        holds another map (saved over it since this one was loaded) says so."""
        try:
            return read_npz(self.root / name, what, expected, self.digests,
                            self.held.pop(name, None))
        except ChecksumMismatch:
            if _meta_identity(self.root) != self.meta_identity:
                raise InputError(f"{self.root}: another map was saved there since this one "
                                 f"was loaded, so its {name} is not this map's; load the map "
                                 "again") from None
            raise

    def session_frames(self) -> dict[str, Rigid3] | None:
        """For a map a SLAM session learned (`slam --out`: recorded poses "slam", its frame
        the session's, not the dataset's): its keyframes' world_from_cam by name (map frame,
        metres), what a dataset's poses are fitted onto to compare with it; None for a map in
        its dataset's frame."""
        recorded = self.info.dataset
        if recorded is None or recorded.poses != "slam":
            return None
        db = self.database
        return {n: Rigid3.from_matrix(m, tol=1e-2, source=f"{self.root}: frame {n}")
                for n, m in zip(db.frame_names, np.asarray(db.world_from_cam).reshape(-1, 4, 4))}

    @cached_property
    def surface(self) -> Surface | None:
        """The fused depth surface, or None for a map built without depth."""
        if SURFACE not in (self.info.files or {}):
            return None
        path = self.root / SURFACE
        if not path.exists() and not path.is_symlink():
            raise InputError(f"{path}: the map lists a surface but the file is missing")
        arrays = self._read_npz(SURFACE, "surface", self.info.files[SURFACE])
        surface = Surface.from_arrays(arrays, str(path))
        if len(surface.points) == 0:  # would be served as a surface that never refines
            raise InputError(f"{path}: the surface holds no points")
        recorded = self.info.surface.n_points if self.info.surface is not None else None
        if recorded is not None and recorded != len(surface.points):
            raise InputError(f"{path}: holds {len(surface.points)} points, but {META} says "
                             f"'surface.n_points' {recorded}")
        return surface

    @cached_property
    def provenance(self) -> MapProvenance | None:
        """Per database row: where the label came from and its training weight; None for a
        map that was never updated. Maps updated before provenance.npz was checksummed are
        read without the checksum."""
        path = self.root / PROVENANCE
        listed = PROVENANCE in (self.info.files or {})
        present = path.exists() or path.is_symlink()
        if not listed and not present:
            return None
        if not present:
            raise InputError(f"{path}: the map lists provenance but the file is missing")
        arrays = self._read_npz(PROVENANCE, "provenance",
                                self.info.files[PROVENANCE] if listed else None)
        check_provenance(arrays, path, len(self.database.points))
        return MapProvenance(arrays["source"].astype(np.int8),
                             arrays["quality"].astype(np.float32))

    def size_bytes(self) -> int:
        """The network: weights + metadata (with the guided refinement, localization also
        reads the database, `database_bytes`)."""
        return ((self.root / self.info.weights_file).stat().st_size
                + (self.root / META).stat().st_size)

    def database_bytes(self) -> int | None:
        """The size of database.npz; None for a map shipped without it (`has_database`)."""
        try:
            return (self.root / DATABASE).stat().st_size
        except FileNotFoundError:
            return None

    @property
    def lists_database(self) -> bool:
        """Whether the metadata lists a training database with its checksum (format 2): a
        reader that must serve the map as written (`slamreloc serve`) refuses it missing."""
        return self.format_version >= 2 and DATABASE in (self.info.files or {})

    @property
    def provenance_unverified(self) -> bool:
        """Whether `provenance` is read without a checksum: the folder holds provenance.npz
        but the metadata does not list it (a map updated before provenance was checksummed,
        or a file dropped in later)."""
        path = self.root / PROVENANCE
        return (PROVENANCE not in (self.info.files or {})
                and (path.exists() or path.is_symlink()))

    @cached_property
    def has_database(self) -> bool:
        """Whether the folder holds its training database (a map can be shipped without it:
        the regressor then localizes without the guided refinement). Decided once, at the
        first ask: a map held in memory (a served one) does not change with its folder."""
        path = self.root / DATABASE
        return path.exists() or path.is_symlink()  # a pipe or a folder there is refused on use
