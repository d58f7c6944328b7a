"""`SlamBackend`: odometry + tracking health + keyframe pose graph in the map frame, with events
for plugins. Feed frames with `process`; relocalization arrives through plugins, which call
`anchor` (recovery after loss), `reanchor` (the track was wrong: kidnapped) or `add_loop_closure`.

Frames: odometry poses are `odom_from_cam` in the frame of the current odometry epoch (a new
epoch starts when tracking is lost and the front end is reset); map-frame poses are
`world_from_cam`. A graph segment is a run of keyframes linked by odometry factors.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum

import numpy as np

from slamreloc.geometry import Rigid3, rotation_angle_deg
from slamreloc.memory import release_free_memory
from slamreloc.slam.anchoring import AnchoringMixin
from slamreloc.slam.events import Event, EventKind, FrameData, Plugin
from slamreloc.slam.graph import GraphConfig, PoseGraph
from slamreloc.slam.health import Health, HealthConfig, check_health
from slamreloc.slam.odometry import Odometry, OdometryStep
from slamreloc.slam.timing import Timer

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


class SlamBackend(AnchoringMixin):
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
                timestamp: float | None = None) -> StepResult:
        """One frame: RGB uint8 (or None), depth in metres (or None), its Camera, and your own
        odometry pose (any fixed odometry frame) if the backend has no front end."""
        index = len(self.frames)
        data = FrameData(index, float(index if timestamp is None else timestamp), image, depth,
                         camera)
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

