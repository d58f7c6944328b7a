"""Backend events and the plugin registry (entry-point group `slamreloc.plugins`).

A plugin is any object with `attach(backend)` and `on_event(event)`; the backend calls
`on_event` for every event, in the order the events happen. Third-party packages register a
factory (a class or a function returning a plugin) under the entry-point group.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum
from importlib import import_module, metadata
from typing import Any, Protocol

import numpy as np

from slamreloc.geometry import Rigid3
from slamreloc.types import Camera

ENTRY_POINT_GROUP = "slamreloc.plugins"
BUILTIN_PLUGINS = {"relocalization": "slamreloc.plugins.relocalization:RelocalizationPlugin"}


class EventKind(str, Enum):
    FRAME = "frame"  # every processed frame, after odometry and the health check
    NEW_KEYFRAME = "new_keyframe"
    TRACKING_LOST = "tracking_lost"
    TRACKING_RECOVERED = "tracking_recovered"
    MAP_UPDATED = "map_updated"  # the graph took a relocalization factor (loop closure)


@dataclass
class FrameData:
    """What the backend was given for one frame: RGB uint8, depth in metres (or None)."""

    index: int
    timestamp: float
    image: np.ndarray | None
    depth: np.ndarray | None
    camera: Camera


@dataclass
class Event:
    kind: EventKind
    frame: int  # index of the frame it happened at
    world_from_cam: Rigid3 | None = None  # map-frame pose of that frame, when known
    info: dict[str, Any] = field(default_factory=dict)


class Plugin(Protocol):
    name: str

    def attach(self, backend: Any) -> None: ...

    def on_event(self, event: Event, frame: FrameData) -> None: ...


def _load(target: str):
    module, _, attr = target.partition(":")
    return getattr(import_module(module), attr)


def available_plugins() -> dict[str, Any]:
    """name -> factory: entry points of the group, then the built-in ones not listed there."""
    found = {ep.name: ep for ep in metadata.entry_points(group=ENTRY_POINT_GROUP)}
    out: dict[str, Any] = {name: ep.load for name, ep in found.items()}
    for name, target in BUILTIN_PLUGINS.items():
        out.setdefault(name, lambda target=target: _load(target))
    return out


def load_plugin(name: str, **kwargs) -> Plugin:
    """Instantiate the plugin registered as `name` with `kwargs`."""
    plugins = available_plugins()
    if name not in plugins:
        raise ValueError(f"unknown plugin '{name}' (known: {', '.join(sorted(plugins))})")
    return plugins[name]()(**kwargs)
