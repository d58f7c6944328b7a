"""The live-mapping plugin: the backend builds the map it relocalizes in.

- A session without a prior map starts its map in the frame of its first frame with depth
  (the backend is anchored there at the identity); one extending a prior map starts lost and
  waits for the relocalization plugin to anchor it in that map.
- Every keyframe with depth adds its labelled rows to the `LiveMap` (keypoints, descriptors,
  points from depth in the keyframe's frame) and hands the learner the database, which trains
  the regressor on its own thread while tracking continues.
- Every `save_every_s` seconds (and at the end, by the caller) the map is written to `out`
  crash-safely (`save_map`: a temporary folder swapped in), once a round has published a
  regressor.

Relocalization itself is the relocalization plugin's, given the `LiveMap` as its localizer:
the same votes and gates as with a prior map; a relocalization against a keyframe older than
`loop_min_frames` becomes a between-factor from that keyframe (a loop closure).
"""

from __future__ import annotations

import time
from contextlib import nullcontext
from pathlib import Path

from slamreloc.geometry import Rigid3
from slamreloc.io.outputs import outputs_now
from slamreloc.map.meta import DatasetMeta
from slamreloc.slam.backend import TrackState
from slamreloc.slam.events import Event, EventKind, FrameData
from slamreloc.slam.live_map import LiveMap


class LiveMappingPlugin:
    name = "live_mapping"

    def __init__(self, live_map: LiveMap, out: str | Path | None = None,
                 dataset: DatasetMeta | None = None, save_every_s: float = 30.0):
        """live_map: the map to grow (`LiveMap`, shared with the relocalization plugin as its
        localizer); out: the map folder written every `save_every_s` seconds (None: never
        written here); dataset: what the saved map records of the dataset tracked."""
        self.live_map, self.out, self.dataset = live_map, out, dataset
        self.save_every_s = save_every_s
        self.start_lost = live_map.prior is not None
        self.n_saves = 0
        self._last_save = time.monotonic()

    def attach(self, backend) -> None:
        self.backend = backend
        self.live_map.attach(backend)

    def on_event(self, event: Event, frame: FrameData) -> None:
        if event.kind == EventKind.FRAME:
            if (self.backend.state == TrackState.INITIALIZING and not self.start_lost
                    and frame.depth is not None and frame.image is not None):
                self.backend.anchor(frame.index, Rigid3.identity())  # the map's frame
            self.live_map.learner.check()
            if (self.out is not None and self.save_every_s > 0
                    and time.monotonic() - self._last_save >= self.save_every_s):
                self.save(at_once=True)
        elif event.kind == EventKind.NEW_KEYFRAME:
            self.live_map.add_keyframe(frame, event.info["key"])

    def save(self, at_once: bool = False) -> Path | None:
        """Write the map (None before the first round has published a regressor, and while a
        session extending a prior map has added no keyframe to it: what it would write is the
        prior map, recording the session's dataset as its own): inside `outputs_together`
        with the command's other outputs, unless `at_once` (a periodic save, or what an
        interrupted session keeps: in place now)."""
        self._last_save = time.monotonic()
        if self.live_map.adds_nothing:
            return None
        with outputs_now() if at_once else nullcontext():
            written = self.live_map.save(self.out, self.dataset)
        self.n_saves += written is not None
        return written
