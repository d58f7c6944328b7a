"""What plugins call on the backend: odometry between frames, map-frame poses, and the three
ways a relocalization enters the graph (anchor after loss, re-anchor, loop closure)."""

from __future__ import annotations

from bisect import bisect_left

from slamreloc.geometry import Rigid3
from slamreloc.slam.events import Event, EventKind


class AnchoringMixin:
    """Mixed into SlamBackend (uses its frames, graph, seg_keys, state and events)."""

    def odometry_between(self, i: int, j: int) -> Rigid3 | None:
        """cam_i_from_cam_j from odometry; None across an odometry reset."""
        a, b = self.frames[i], self.frames[j]
        return a.odom_from_cam.inverse() @ b.odom_from_cam if a.epoch == b.epoch else None

    def _nearest_keyframe(self, i: int) -> int | None:
        keys = self.seg_keys.get(self.frames[i].segment)
        if not keys:
            return None
        pos = bisect_left(keys, i)
        near = [keys[p] for p in (pos - 1, pos) if 0 <= p < len(keys)]
        return min(near, key=lambda k: abs(k - i))

    def pose_of(self, i: int) -> Rigid3 | None:
        """Current map-frame world_from_cam of frame i (None if its track is not anchored)."""
        k = self._nearest_keyframe(i)
        if k is None:
            return None
        return self.graph.pose(self.frames[k].key) @ self.odometry_between(k, i)

    def _new_segment(self, first: int, world_from_cam_i: Rigid3, i: int,
                     also: list[tuple[int, Rigid3]]) -> int:
        """Frames first..newest (one epoch) become a new segment anchored at the newest frame."""
        from slamreloc.slam.backend import TrackState

        seg = self.n_segments
        self.n_segments += 1
        cur = self.frames[-1]
        for rec in self.frames[first:]:
            if rec.key is not None:
                self.seg_keys[rec.segment].remove(rec.index)
            rec.segment, rec.key = seg, None
        self.segment = seg
        self.state = TrackState.TRACKING
        with self.timer("graph"):
            self._add_keyframe(cur, prior=world_from_cam_i @ self.odometry_between(i, cur.index))
            for j, world_from_cam_j in also:
                self.graph.add_prior(cur.key, world_from_cam_j @ self.odometry_between(
                    j, cur.index))
        return cur.index

    def anchor(self, i: int, world_from_cam_i: Rigid3,
               also: list[tuple[int, Rigid3]] = ()) -> None:
        """Tracking was lost (or never started): place the current odometry epoch in the map
        frame so that frame i has `world_from_cam_i`; `also` adds the agreeing relocalizations."""
        first = self.epoch_first  # not a scan of every frame of the run
        cur = self._new_segment(first, world_from_cam_i, i, list(also))
        self._emit(Event(EventKind.TRACKING_RECOVERED, cur, self.pose_of(cur),
                                  {"relocalized_frame": i}))

    def reanchor(self, i: int, world_from_cam_i: Rigid3,
                 also: list[tuple[int, Rigid3]] = (), reason: str = "") -> None:
        """The track is wrong from frame i on (an unnoticed kidnapping): cut the graph there
        and anchor frames i..newest anew."""
        first = min([i, *(j for j, _ in also)])
        self._emit(Event(EventKind.TRACKING_LOST, first, None, {"reason": reason}))
        cur = self._new_segment(first, world_from_cam_i, i, list(also))
        self._emit(Event(EventKind.TRACKING_RECOVERED, cur, self.pose_of(cur),
                                  {"relocalized_frame": i, "reanchor": True}))

    def add_loop_closure(self, i: int, world_from_cam_i: Rigid3,
                         sigma_scale: float = 1.0) -> None:
        """An accepted relocalization of frame i (tracked): a robust prior on its keyframe
        (sigmas: the graph's relocalization sigmas times `sigma_scale`)."""
        k = self._nearest_keyframe(i)
        if k is None:
            raise ValueError(f"frame {i} is not on an anchored track")
        with self.timer("graph"):
            self.graph.add_prior(self.frames[k].key,
                                 world_from_cam_i @ self.odometry_between(i, k), sigma_scale)
        self._emit(Event(EventKind.MAP_UPDATED, i, self.pose_of(i),
                                  {"keyframe": k}))
