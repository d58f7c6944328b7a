"""Backend events and the plugin registry (entry-point group `slamreloc.plugins`).

A plugin is any object with `attach(backend)` and `on_event(event)`; the backend calls
`on_event` for every event, in the order the events happen. Every plugin, the built-in
relocalization plugin included, is found through the entry-point group: a package registers a
factory (a class or a function returning a plugin) under it in its pyproject.toml, as
slamreloc's own does. The backend never names a plugin's module.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum
from importlib import metadata
from typing import Any, Protocol

import numpy as np

from slamreloc.geometry import Rigid3
from slamreloc.types import Camera

ENTRY_POINT_GROUP = "slamreloc.plugins"


class EventKind(str, Enum):
    FRAME = "frame"  # every processed frame, after odometry and the health check
    NEW_KEYFRAME = "new_keyframe"
    TRACKING_LOST = "tracking_lost"
    TRACKING_RECOVERED = "tracking_recovered"
    MAP_UPDATED = "map_updated"  # the graph took a relocalization factor (loop closure)


@dataclass
class FrameData:
    """What the backend was given for one frame: RGB uint8 (H, W, 3) or None, its `camera`
    (pixels), the timestamp (seconds), and depth (float32 metres along z, 0 = none; or None)
    in the pixels of `depth_camera`: the camera that took it (`Frame.depth_camera`; scaled to
    the depth map where its size differs) where it is not registered to the image; None:
    registered (the image's `camera`, scaled to the depth map). `rgb_from_depth`: that depth
    camera's pose in the RGB camera's frame (`Frame.rgb_from_depth`, metres; None: identity);
    `name`: the frame's name in its dataset (None: unnamed)."""

    index: int
    timestamp: float
    image: np.ndarray | None
    depth: np.ndarray | None
    camera: Camera
    depth_camera: Camera | None = None
    rgb_from_depth: Rigid3 | None = None
    name: str | None = None


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


def available_plugins() -> dict[str, Any]:
    """name -> factory, for every entry point of the group `slamreloc.plugins`."""
    return {ep.name: ep.load for ep in metadata.entry_points(group=ENTRY_POINT_GROUP)}


def load_plugin(name: str, **kwargs) -> Plugin:
    """Instantiate the plugin registered as `name` with `kwargs`."""
    plugins = available_plugins()
    if name not in plugins:
        known = ", ".join(sorted(plugins)) or "none: is slamreloc installed (pip install -e .)?"
        raise ValueError(f"unknown plugin '{name}' (entry-point group {ENTRY_POINT_GROUP}; "
                         f"known: {known})")
    return plugins[name]()(**kwargs)
