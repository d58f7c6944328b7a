"""Test harness: the relocalization plugin with a share of its results replaced by wrong poses.

`FaultInjectingRelocalization` is `RelocalizationPlugin` whose candidates (PnP + ICP results,
before the quality gate) are, with probability `wrong_fraction` each, moved at least 0.5 m or
20 deg off and marked `injected`; the gate, the votes and the track checks must then reject
every one (the plugin's stats count them: n_injected, _rejected, _accepted). One random stream
(`seed`) decides which and how, so a run is reproducible.

Used by tests/test_slam.py and by benchmarks/slam_targets.py (run from the repository root as
`python -m benchmarks.slam_targets`, like the viewer benchmark's use of tests/browser.py); it
is not part of the installed package, and the production plugin's config has no such hook.
"""

from __future__ import annotations

import numpy as np

from slamreloc.geometry import Rigid3, axis_angle_to_matrix
from slamreloc.plugins.gating import Candidate
from slamreloc.plugins.relocalization import RelocalizationPlugin
from slamreloc.slam.events import FrameData


class FaultInjectingRelocalization(RelocalizationPlugin):
    """`RelocalizationPlugin(*args, **kwargs)` with `wrong_fraction` of its results wrong."""

    def __init__(self, *args, wrong_fraction: float, seed: int = 0, **kwargs):
        super().__init__(*args, **kwargs)
        self.wrong_fraction = wrong_fraction
        self._rng = np.random.default_rng(seed)

    def candidate(self, frame: FrameData) -> Candidate | None:
        c = super().candidate(frame)
        if c is not None and self._rng.random() < self.wrong_fraction:
            c.world_from_cam, c.injected = self._wrong(c.world_from_cam), True
        return c

    def _wrong(self, world_from_cam: Rigid3) -> Rigid3:
        """A pose at least 0.5 m or 20 deg from the given one."""
        axis = self._rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        if self._rng.random() < 0.5:
            return Rigid3(world_from_cam.rotation,
                          world_from_cam.translation + axis * self._rng.uniform(0.5, 1.0))
        rot = axis_angle_to_matrix(axis * np.radians(self._rng.uniform(20, 40)))
        return Rigid3(world_from_cam.rotation @ rot, world_from_cam.translation)
