"""The relocalization plugin: the core's regressor + PnP inside the SLAM backend.

(a) Kidnapped recovery: while the backend is lost (or not yet started) every incoming frame is
    relocalized; once `votes` (3) relocalizations agree through odometry the backend is anchored.
(b) Loop closure: `loop_closure_every` keyframes after the last accepted relocalization the
    keyframe is relocalized (the schedule restarts at each acceptance, so a rejected result
    delays the next closure by a frame, not by a whole period); a result
    that fits the track becomes a robust prior in the graph. One that does not fit is held
    and the next frames are relocalized: if a later one agrees with it the track was wrong
    (re-anchor: `reanchor_votes`, 4, in all), if not within the window they are rejected.
Inputs to every decision: the PnP inlier count and the regressor's confidence (gating.py).
Where the frame has depth and the map a surface (slamreloc.map.surface), each PnP pose is refined by
point-to-plane ICP against the map's surface before it is judged (`refine_with_depth`, the
depth camera from `FrameData.depth_camera`; RedKitchen: recovered poses 6.3 -> ~1-2 cm); a fit
that does not converge onto the surface leaves the PnP pose as it was.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from slamreloc.plugins.gating import Candidate, GateConfig, find_agreeing, fits_track, good_quality
from slamreloc.plugins.relocstats import RelocStats

from slamreloc.geometry import Rigid3
from slamreloc.slam.backend import TrackState
from slamreloc.slam.events import Event, EventKind, FrameData
from slamreloc.slam.live_map import LiveMap
from slamreloc.map.surface import IcpConfig, refine_with_depth


@dataclass(frozen=True)
class RelocalizationConfig:
    gate: GateConfig = field(default_factory=GateConfig)
    loop_closure_every: int = 3  # keyframes from an accepted relocalization to the next try
    # a loop closure between keyframes of a map being built: its sigmas are the graph's
    # relocalization sigmas times this (its points come from depth, not a regressor; 0.5 on
    # the RedKitchen stream: ATE 3.8 -> 3.1 cm, chosen on the stream BENCHMARKS.md reports)
    keyframe_loop_sigma_scale: float = 0.5
    keep_fraction: float = 0.5  # PnP on this share of the most confident predictions (localizer)
    # the depth refinement of PnP poses (`refine_with_depth`); None: no depth refinement
    icp: IcpConfig | None = field(default_factory=IcpConfig)


class RelocalizationPlugin:
    name = "relocalization"

    def __init__(self, map_dir: str | Path | None = None, localizer=None,
                 config: RelocalizationConfig = RelocalizationConfig(), device: str = "cpu",
                 scene_map=None):
        """The map to relocalize in, one of: `map_dir` (a map folder, loaded here),
        `scene_map` (a loaded `SceneMap`, e.g. one a server already holds) or `localizer`
        (a ready localizer). Each frame's depth comes with its camera (`FrameData`)."""
        if localizer is None:
            from slamreloc.localize.localizer import RegressorLocalizer

            if scene_map is None:
                from slamreloc.map.scene_map import SceneMap

                scene_map = SceneMap.load(map_dir)
            localizer = RegressorLocalizer(scene_map, device=device,
                                           keep_fraction=config.keep_fraction)
        self.localizer, self.config = localizer, config
        self.surface = localizer.map.surface if config.icp is not None else None
        self.stats = RelocStats()
        self.pending: list[Candidate] = []  # tracking: candidates that do not fit the track
        self.lost: list[Candidate] = []  # lost: candidates waiting for an agreeing one
        self._keyframes_since, self._keyframe_due = 0, False  # since the last acceptance

    def attach(self, backend) -> None:
        self.backend = backend

    def on_event(self, event: Event, frame: FrameData) -> None:
        if event.kind == EventKind.NEW_KEYFRAME:
            self._keyframes_since += 1
            self._keyframe_due = self._keyframes_since >= self.config.loop_closure_every
        elif event.kind == EventKind.TRACKING_LOST:
            self._reject(self.pending)
        elif event.kind == EventKind.FRAME:
            due, self._keyframe_due = self._keyframe_due, False
            if self.backend.state == TrackState.TRACKING:
                if due or self.pending or event.info.get("health") == "suspect":
                    self._while_tracking(frame)
            else:
                self._while_lost(frame)

    def _while_lost(self, frame: FrameData) -> None:
        c = self.relocalize(frame)
        if c is None:
            return
        agreeing = find_agreeing(c, self.lost, self.backend, self.config.gate)
        if len(agreeing) + 1 >= self.config.gate.votes:
            self.backend.anchor(c.frame, c.world_from_cam,
                                [(a.frame, a.world_from_cam) for a in agreeing])
            self.stats.accept([c, *agreeing], "anchor")
            self._keyframes_since = 0
            self._reject([x for x in self.lost if x not in agreeing])
            self.lost = []
        else:
            self.lost = self._age([*self.lost, c], c.frame)

    def _while_tracking(self, frame: FrameData) -> None:
        c = self.relocalize(frame)
        if c is None:
            self.pending = self._age(self.pending, frame.index)
            return
        if fits_track(c, self.backend, self.config.gate):
            self.stats.accept([c], self._close_loop(c))
            self._keyframes_since = 0
            self._reject(self.pending)
            return
        agreeing = find_agreeing(c, self.pending, self.backend, self.config.gate)
        if len(agreeing) + 1 >= self.config.gate.reanchor_votes:
            # consistent with each other, not with the track: the track is wrong
            others = [x for x in self.pending if x not in agreeing]
            self.pending = []  # the re-anchor's tracking_lost event must not reject the voters
            self.backend.reanchor(c.frame, c.world_from_cam,
                                  [(a.frame, a.world_from_cam) for a in agreeing],
                                  reason="relocalizations agree with each other, not the track")
            self.stats.accept([c, *agreeing], "reanchor")
            self._keyframes_since = 0
            self._reject(others)
        else:
            self.pending = self._age([*self.pending, c], c.frame)

    def _close_loop(self, c: Candidate) -> str:
        """Put a relocalization that fits the track into the graph; returns how: a prior in
        the map's fixed frame (a prior map's, or a frame a live map took over from one), a
        between-factor from the keyframe of the map being built that its inliers mostly came
        from (a loop query only uses old keyframes: `LiveMap.localize_query`), or nothing (a
        live map's result that names no keyframe: it confirms the track)."""
        ref = c.reference
        if not c.live or (ref is not None and ref.key is None):
            self.backend.add_loop_closure(c.frame, c.world_from_cam)
            return "loop_closure"
        if ref is not None:
            self.backend.add_keyframe_loop(c.frame, ref.key, ref.key_from_cam,
                                           self.config.keyframe_loop_sigma_scale)
            return "keyframe_loop"
        return "confirmation"

    def _age(self, cands: list[Candidate], now: int) -> list[Candidate]:
        """Drop (and count as rejected) candidates too old to be confirmed."""
        old = [c for c in cands if now - c.frame >= self.config.gate.window]
        self._reject(old)
        return [c for c in cands if c not in old]

    def _reject(self, cands: list[Candidate]) -> None:
        self.stats.reject(cands)
        self.pending = [c for c in self.pending if c not in cands]

    def relocalize(self, frame: FrameData) -> Candidate | None:
        """Regressor + PnP on the frame's image; None when PnP fails or quality is too low."""
        c = self.candidate(frame)
        if c is None:
            return None
        if not good_quality(c, self.config.gate):
            self.stats.n_failed += 1
            return None
        return c

    def candidate(self, frame: FrameData) -> Candidate | None:
        """The frame's relocalization before the quality gate: regressor + PnP, refined by ICP
        onto the map's surface where the frame has depth; None when PnP fails."""
        loc = self.localizer
        with self.backend.timer("relocalization"):
            live = isinstance(loc, LiveMap)  # a map the session builds
            feats = (loc.features(frame) if live  # shared with its keyframe rows
                     else loc.extractor.extract(frame.image, frame.camera))
            result = (loc.localize_query(feats, frame.camera, frame.index,
                                         loop_only=self.backend.state == TrackState.TRACKING)
                      if live else loc.localize_features(feats, frame.camera))
            est, world_from_cam = result.estimate, result.estimate.world_from_cam
            if est.success and self.surface is not None and frame.depth is not None:
                world_from_cam = self._refine(frame, world_from_cam)
        self.stats.n_attempts += 1
        if not est.success:
            self.stats.n_failed += 1
            return None
        confidence = 1.0 if result.inlier_confidence is None else result.inlier_confidence
        return Candidate(frame.index, world_from_cam, est.num_inliers, confidence, live=live,
                         reference=getattr(result, "reference", None))

    def _refine(self, frame: FrameData, world_from_cam: Rigid3) -> Rigid3:
        """The frame's depth fitted onto the map's surface from the PnP pose (world_from_cam,
        map frame, metres); the PnP pose where the fit is not accepted."""
        with self.backend.timer("icp"):
            fit = refine_with_depth(self.surface, frame.depth, frame.camera, frame.depth_camera,
                                    world_from_cam, self.config.icp)
        self.stats.n_refined += fit.accepted
        return fit.chosen()

    def finish(self) -> None:
        """End of the run: candidates still waiting for confirmation count as rejected."""
        self._reject([*self.pending, *self.lost])
        self.lost = []
