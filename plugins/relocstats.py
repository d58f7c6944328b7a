"""Counters of the relocalization plugin, for the SLAM report."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

from slamreloc.plugins.gating import Candidate


@dataclass
class RelocStats:
    n_attempts: int = 0  # relocalizations run
    n_failed: int = 0  # PnP failed or inliers / confidence too low
    n_refined: int = 0  # PnP poses moved onto the map's surface by ICP (depth)
    n_loop_closures: int = 0  # accepted while tracking (fit the track)
    # of those, against a keyframe of the map being built: between-factors in the graph
    n_keyframe_loops: int = 0
    # accepted while tracking against the track's own recent keyframes (a live map): they
    # confirm the track and add nothing to the graph
    n_confirmations: int = 0
    n_anchors: int = 0  # confirmed after tracking loss
    n_reanchors: int = 0  # confirmed against the track
    n_rejected: int = 0  # never confirmed
    n_injected: int = 0  # wrong poses injected by the test harness (with enough inliers)
    n_injected_rejected: int = 0
    n_injected_accepted: int = 0
    accepted_frames: list[int] = field(default_factory=list)
    # every decision, for the report's event list (the viewer draws them)
    decisions: list[dict] = field(default_factory=list)

    def _record(self, cands: list[Candidate], kind: str, accepted: bool) -> None:
        self.decisions += [{"frame": c.frame, "type": kind, "accepted": accepted,
                            "num_inliers": c.num_inliers, "confidence": round(c.confidence, 3),
                            "position": [round(float(v), 4) for v in c.world_from_cam.translation]}
                           for c in cands]

    def accept(self, cands: list[Candidate], how: str) -> None:
        if how in ("loop_closure", "keyframe_loop"):
            self.n_loop_closures += 1
            self.n_keyframe_loops += how == "keyframe_loop"
        elif how == "confirmation":
            self.n_confirmations += 1
        elif how == "anchor":
            self.n_anchors += 1
        else:
            self.n_reanchors += 1
        for c in cands:
            self.n_injected += c.injected
            self.n_injected_accepted += c.injected
            self.accepted_frames.append(c.frame)
        kind = {"keyframe_loop": "loop_closure", "confirmation": "confirmation"}.get(how, how)
        self._record(cands, kind if kind in ("loop_closure", "confirmation")
                     else "relocalization", True)

    def reject(self, cands: list[Candidate]) -> None:
        for c in cands:
            self.n_rejected += 1
            self.n_injected += c.injected
            self.n_injected_rejected += c.injected
        self._record(cands, "relocalization", False)

    def to_dict(self) -> dict:
        d = asdict(self)
        d.pop("accepted_frames")
        d.pop("decisions")
        return d
