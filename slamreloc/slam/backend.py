"""`SlamBackend`: odometry + tracking health + keyframe pose graph in the map frame, with events
for plugins. Feed frames with `process`; relocalization arrives through plugins, which call
`anchor` (recovery after loss), `reanchor` (the track was wrong: kidnapped) or `add_loop_closure`.

Frames: odometry poses are `odom_from_cam` in the frame of the current odometry epoch (a new
epoch starts when tracking is lost and the front end is reset); map-frame poses are
`world_from_cam`. A graph segment is a run of keyframes linked by odometry factors.
"""

from __future__ import annotations

from bisect import bisect_left
from dataclasses import dataclass, field
from enum import Enum

import numpy as np

from slamreloc.geometry import Rigid3, rotation_angle_deg
from slamreloc.runtime.memory import release_free_memory
from slamreloc.slam.events import Event, EventKind, FrameData, Plugin
from slamreloc.slam.graph import GraphConfig, PoseGraph
from slamreloc.slam.health import Health, HealthConfig, check_health
from slamreloc.slam.odometry import Odometry, OdometryStep
from slamreloc.slam.timing import Timer
from slamreloc.types import Camera

LOGGED_EVENTS = frozenset({EventKind.TRACKING_LOST, EventKind.TRACKING_RECOVERED,
                           EventKind.MAP_UPDATED})


class TrackState(str, Enum):
    INITIALIZING = "initializing"  # no map-frame pose yet
    TRACKING = "tracking"
    LOST = "lost"


@dataclass(frozen=True)
class BackendConfig:
    keyframe_every: int = 3  # frames between keyframes inside a segment
    release_memory_every: int = 100  # frames; hand freed heap back to the OS (0: never)
    health: HealthConfig = field(default_factory=HealthConfig)
    graph: GraphConfig = field(default_factory=GraphConfig)


@dataclass(slots=True)
class FrameRecord:
    """What the backend keeps of a processed frame (never its image or depth)."""

    index: int
    timestamp: float
    epoch: int  # odometry epoch
    segment: int  # graph segment (-1 while not anchored)
    odom_from_cam: Rigid3
    motion: Rigid3  # cam_prev_from_cam reported by odometry (identity at an epoch start)
    health: Health
    key: int | None = None  # graph key when this frame is a keyframe
    online_world_from_cam: Rigid3 | None = None  # the pose returned when it was processed


@dataclass
class StepResult:
    index: int
    world_from_cam: Rigid3 | None  # map frame; None until the first anchor
    state: TrackState
    events: list[Event]


class SlamBackend:
    """Hosts odometry (or takes yours), the pose graph and the plugins."""

    def __init__(self, odometry: Odometry | None = None, plugins: list[Plugin] = (),
                 config: BackendConfig = BackendConfig()):
        self.config, self.odometry = config, odometry
        self.graph = PoseGraph(config.graph)
        self.frames: list[FrameRecord] = []
        self.state = TrackState.INITIALIZING
        self.epoch, self.segment, self._next_key = 0, -1, 0
        self.epoch_first = 0  # index of the first frame of the current odometry epoch
        self.seg_keys: dict[int, list[int]] = {}  # segment -> its keyframes' frame indices
        self.n_segments = 0
        self.timer = Timer()
        self._events: list[Event] = []
        # the run's state changes, in order (not the per-frame and keyframe events: those go
        # to the plugins and into StepResult.events only, so the log does not grow per frame)
        self.event_log: list[Event] = []
        self.plugins = list(plugins)
        for plugin in self.plugins:
            plugin.attach(self)

    # ---- per frame -------------------------------------------------------------------------
    def process(self, image, depth, camera, odometry_world_from_cam: Rigid3 | None = None,
                timestamp: float | None = None, depth_camera: Camera | None = None,
                rgb_from_depth: Rigid3 | None = None, name: str | None = None) -> StepResult:
        """One frame: RGB uint8 (or None), depth in metres (or None), its Camera, and your own
        odometry pose (any fixed odometry frame) if the backend has no front end; timestamp in
        seconds. `depth_camera`: the camera that took the depth (in the depth map's pixel size)
        where it is not registered to the image, else None, placed by `rgb_from_depth`; `name`:
        the frame's name (as `FrameData`)."""
        index = len(self.frames)
        data = FrameData(index, float(index if timestamp is None else timestamp), image, depth,
                         camera, depth_camera, rgb_from_depth, name)
        self._events, self._data = [], data
        with self.timer("odometry"):
            step = self._odometry(data, odometry_world_from_cam)
        prev = self.frames[-1] if self.frames else None
        motion = (prev.odom_from_cam.inverse() @ step.odom_from_cam
                  if prev is not None and prev.epoch == self.epoch else None)
        report = check_health(step, motion, self.config.health, self._recent_motion())
        if report.verdict == Health.LOST:
            self._lose(index, report.reason)
            if odometry_world_from_cam is None and self.odometry is not None:
                with self.timer("odometry"):
                    step = self.odometry.step(depth, camera, image, data.timestamp, index)
            motion = None
        rec = FrameRecord(index, data.timestamp, self.epoch, self.segment, step.odom_from_cam,
                          motion or Rigid3.identity(), report.verdict)
        self.frames.append(rec)
        with self.timer("graph"):
            if self.state == TrackState.TRACKING and self._due_keyframe(rec):
                self._add_keyframe(rec)
        self._emit(Event(EventKind.FRAME, index, self.pose_of(index),
                         {"health": report.verdict.value, "reason": report.reason,
                          "fitness": step.fitness, "state": self.state.value}))
        rec.online_world_from_cam = self.pose_of(index)
        every = self.config.release_memory_every
        if every and (index + 1) % every == 0:
            release_free_memory()  # a run of days must not grow with the allocator's slack
        return StepResult(index, rec.online_world_from_cam, self.state, self._events)

    def finish(self) -> None:
        """End of the run: let plugins settle pending work, then optimise the whole graph."""
        for plugin in self.plugins:
            getattr(plugin, "finish", lambda: None)()
        with self.timer("final_optimization"):
            self.graph.optimize_batch()

    # ---- what plugins call: odometry between frames, map-frame poses, and the three ways a
    # relocalization enters the graph (anchor after loss, re-anchor, loop closure) -----------
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
        self._emit(Event(EventKind.MAP_UPDATED, i, self.pose_of(i), {"keyframe": k}))

    def add_keyframe_loop(self, i: int, key: int, key_from_cam_i: Rigid3,
                          sigma_scale: float = 1.0) -> None:
        """An accepted relocalization of frame i (tracked) against graph keyframe `key` of a
        map this session builds: frame i seen from that keyframe (cam_key_from_cam_i,
        metres), a robust between-factor from it to frame i's keyframe."""
        k = self._nearest_keyframe(i)
        if k is None:
            raise ValueError(f"frame {i} is not on an anchored track")
        with self.timer("graph"):
            self.graph.add_between(key, self.frames[k].key,
                                   key_from_cam_i @ self.odometry_between(i, k), sigma_scale)
        self._emit(Event(EventKind.MAP_UPDATED, i, self.pose_of(i),
                         {"keyframe": k, "loop_to_key": key}))

    def keyframe_pose(self, key: int) -> Rigid3:
        """The current map-frame world_from_cam of graph keyframe `key`."""
        return self.graph.pose(key)

    # ---- internals -------------------------------------------------------------------------
    def _recent_motion(self, n: int = 10) -> tuple[float, float]:
        """Median motion per frame (metres, degrees) over the last n frames of this epoch."""
        recent = [f.motion for f in self.frames[-n:] if f.epoch == self.epoch
                  and f.health == Health.OK]
        if len(recent) < 3:
            return 0.0, 0.0
        return (float(np.median([np.linalg.norm(m.translation) for m in recent])),
                float(np.median([rotation_angle_deg(m.rotation) for m in recent])))

    def _odometry(self, data: FrameData, given: Rigid3 | None) -> OdometryStep:
        if given is not None:
            return OdometryStep(given)
        if self.odometry is None:
            raise ValueError("no odometry: pass odometry_world_from_cam or an Odometry")
        return self.odometry.step(data.depth, data.camera, data.image, data.timestamp,
                                  data.index)

    def _due_keyframe(self, rec: FrameRecord) -> bool:
        keys = self.seg_keys.get(rec.segment)
        return (not keys or rec.index - keys[-1] >= self.config.keyframe_every
                or rec.health == Health.SUSPECT)

    def _add_keyframe(self, rec: FrameRecord, prior: Rigid3 | None = None) -> None:
        """Make `rec` (the newest frame of its segment) a graph node."""
        keys = self.seg_keys.setdefault(rec.segment, [])
        last = self.frames[keys[-1]] if keys else None
        key = self._next_key
        self._next_key += 1
        if last is None:
            self.graph.add_node(key, prior, prior=prior)
        else:
            prev_from_cur = last.odom_from_cam.inverse() @ rec.odom_from_cam
            self.graph.add_node(key, self.graph.pose(last.key) @ prev_from_cur, last.key,
                                prev_from_cur, prior)
        rec.key = key
        keys.append(rec.index)
        self._emit(Event(EventKind.NEW_KEYFRAME, rec.index, self.graph.pose(key), {"key": key}))

    def _lose(self, index: int, reason: str) -> None:
        if self.state == TrackState.TRACKING:
            self._emit(Event(EventKind.TRACKING_LOST, index, None, {"reason": reason}))
            self.state = TrackState.LOST
        self.epoch += 1
        self.epoch_first = index
        self.segment = -1
        if self.odometry is not None:
            self.odometry.reset()

    def _emit(self, event: Event) -> None:
        """Record an event and hand it to every plugin (with the frame being processed)."""
        self._events.append(event)
        if event.kind in LOGGED_EVENTS:
            self.event_log.append(event)
        for plugin in self.plugins:
            plugin.on_event(event, self._data)

