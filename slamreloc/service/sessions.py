"""A running SLAM system's session: its frames go through the same `SlamBackend` and
relocalization plugin as `slamreloc slam`, and what they decide comes back as events.

The session is opened with a map and an odometry source: "client" (each frame carries the
client's own odometry pose, `odometry_world_from_cam`, in its fixed odometry frame: the backend
runs without a front end) or a server front end that tracks the streamed depth ("auto",
"kiss-icp", "open3d", as `slamreloc slam --odometry`). File or topic odometry is not offered:
a client never names a file on the server.

A learning session (`SessionOpen.learn`, no map) runs what `slamreloc slam --out` runs: a
`LiveMap` without a prior, grown by the `live_mapping` plugin from every keyframe's depth and
relocalized in by the relocalization plugin; its map is anchored at the first frame with depth.
Every frame needs depth (its rows are lifted from it) and the first one a camera (later frames
default to it); every frame is of that one camera, the map's (`map.joining`). `save` writes
the map as `slam --out` does at its end (a training round on the keyframes' current poses,
waited for: `train_for_save`, then every row at those poses: `write`) without ending the
session.
"""

from __future__ import annotations

import contextlib
import json
import math
import time
import uuid

from slamreloc.errors import InputError
from slamreloc.geometry import STAMP_TOLERANCE_S, check_stamp
from slamreloc.io.images import depth_units_problem
from slamreloc.map.joining import ONE_CAMERA
from slamreloc.proto import relocalizer_pb2 as pb
from slamreloc.proto.messages import (
    SAVE_WAIT_S,
    ServiceError,
    camera_from_msg,
    check_depth_camera,
    depth_camera_from_msg,
    depth_from_msg,
    image_from_msg,
    quoted,
    rigid_from_msg,
    transform_msg,
)
from slamreloc.service.maps import ServedMap
from slamreloc.slam.backend import BackendConfig, SlamBackend, TrackState
from slamreloc.slam.events import EventKind, load_plugin
from slamreloc.slam.live_map import LiveMap, LiveMapConfig
from slamreloc.slam.poses import final_trajectory
from slamreloc.slam.run import make_odometry

CLIENT_ODOMETRY = "client"
SERVER_ODOMETRY = ("auto", "kiss-icp", "open3d")
STATES = {TrackState.INITIALIZING: pb.INITIALIZING, TrackState.TRACKING: pb.TRACKING,
          TrackState.LOST: pb.LOST}
EVENTS = {EventKind.TRACKING_LOST: pb.SessionEvent.TRACKING_LOST,
          EventKind.TRACKING_RECOVERED: pb.SessionEvent.TRACKING_RECOVERED,
          EventKind.MAP_UPDATED: pb.SessionEvent.LOOP_CLOSURE,
          EventKind.NEW_KEYFRAME: pb.SessionEvent.NEW_KEYFRAME}


class Session:
    """One client's backend + relocalization plugin on one map (the map version it opened), or
    (`served` None) on the map it learns (`live`: its `LiveMapConfig`)."""

    # a save before the first training round has ended waits this long for it
    SAVE_WAIT_S = SAVE_WAIT_S  # each of the two rounds a save waits for (seconds)

    def __init__(self, served: ServedMap | None, request: pb.SessionOpen,
                 live: LiveMapConfig | None = None):
        odometry = request.odometry or CLIENT_ODOMETRY
        if odometry not in (CLIENT_ODOMETRY, *SERVER_ODOMETRY):
            raise ServiceError(pb.BAD_REQUEST, f"odometry {quoted(odometry)}: one of "
                               f"{', '.join((CLIENT_ODOMETRY, *SERVER_ODOMETRY))}")
        # the camera of the frames' depth where it is not registered to the images, else None
        self.depth_camera = (depth_camera_from_msg(request.depth_camera, "depth_camera")
                             if request.HasField("depth_camera") else None)
        self._depth_camera_msg = pb.PinholeCamera()
        self._depth_camera_msg.CopyFrom(request.depth_camera)
        units = request.depth_units_per_metre
        problem = depth_units_problem(units) if units else None  # 0: 1000
        if problem:
            raise ServiceError(pb.BAD_DEPTH, f"depth_units_per_metre {problem}")
        self.depth_units = units
        self.served, self.id = served, uuid.uuid4().hex[:12]
        self.client_odometry = odometry == CLIENT_ODOMETRY
        front_end = (None if self.client_odometry
                     else make_odometry(odometry, self.depth_camera))
        self.odometry_name = odometry if front_end is None else front_end.name
        self.live_map: LiveMap | None = None
        self.camera = None if served is None else served.scene_map.camera  # frames' default
        self.last_stamp: float | None = None  # the last accepted frame's (0: none given)
        self.stamps_all_zero = True  # every accepted frame's timestamp 0 so far
        if served is None:  # learning: the map grows from the frames (as `slam --out`)
            self.live_map = LiveMap(live or LiveMapConfig())
            self.mapper = load_plugin("live_mapping", live_map=self.live_map, out=None)
            plugin = load_plugin("relocalization", localizer=self.live_map)
            plugins = [self.mapper, plugin]
        else:
            plugin = load_plugin("relocalization", scene_map=self.served.scene_map)
            plugins = [plugin]
        self.plugin = plugin
        self.backend = SlamBackend(front_end, plugins, BackendConfig())
        self._decisions_sent = 0

    @property
    def n_frames(self) -> int:
        """Frames processed so far: the index the next frame gets."""
        return len(self.backend.frames)

    @property
    def learning(self) -> bool:
        return self.live_map is not None

    def opened(self) -> pb.SessionOpened:
        return pb.SessionOpened(session_id=self.id, odometry=self.odometry_name,
                                map_version="" if self.served is None else self.served.version)

    def frame(self, msg: pb.SessionFrame) -> pb.FrameResult:
        """Check and process one frame; ServiceError (nothing processed) for a defective one."""
        loc = self.plugin.localizer
        image = image_from_msg(msg.image, loc.extractor.check_size, "frame.image")
        h, w = image.shape[:2]
        if self.camera is None and not msg.HasField("camera"):
            raise ServiceError(pb.BAD_CAMERA, "frame.camera: required in a learning session's "
                               "first frame (there is no map camera; later frames default to it)")
        camera = camera_from_msg(msg.camera if msg.HasField("camera") else None, w, h,
                                 self.camera, "frame.camera")
        if self.learning and self.camera is not None and not self.camera.same_as(camera):
            raise ServiceError(pb.BAD_CAMERA, f"frame.camera: {camera.describe()} (this "
                               f"frame's), while the session's map is of "
                               f"{self.camera.describe()} (its first frame's): "
                               f"{ONE_CAMERA}; a learning session's frames are of one camera")
        depth = None
        if msg.HasField("depth"):
            if msg.depth.HasField("depth_camera"):
                raise ServiceError(pb.BAD_DEPTH, "frame.depth: the depth camera is given once, "
                                   "in SessionOpen.depth_camera")
            units = msg.depth.units_per_metre
            if (units and self.depth_units and msg.depth.encoding != pb.Depth.FLOAT32_METRES
                    and not math.isclose(units, self.depth_units, rel_tol=1e-6)):
                raise ServiceError(pb.BAD_DEPTH, f"frame.depth.units_per_metre {units:.10g} "
                                   "differs from SessionOpen.depth_units_per_metre "
                                   f"{self.depth_units:.10g}: give the units once (in "
                                   "SessionOpen, or in every frame with none there)")
            depth = depth_from_msg(msg.depth, (w, h) if self.depth_camera is None else None,
                                   self.depth_units, "frame.depth")
            if self.depth_camera is not None:
                check_depth_camera(self._depth_camera_msg, depth, "SessionOpen.depth_camera")
        elif self.learning:
            raise ServiceError(pb.BAD_DEPTH, "frame.depth: a learning session needs depth in "
                               "every frame (the map's points are lifted from it)")
        elif not self.client_odometry:
            raise ServiceError(pb.BAD_DEPTH, f"frame.depth: {self.odometry_name} odometry "
                               "needs depth in every frame")
        odom = None
        if self.client_odometry:
            if not msg.HasField("odometry_world_from_cam"):
                raise ServiceError(pb.BAD_POSE, "frame.odometry_world_from_cam: required with "
                                   "client odometry")
            odom = rigid_from_msg(msg.odometry_world_from_cam, "frame.odometry_world_from_cam")
        try:
            check_stamp(msg.timestamp, "frame.timestamp")  # the rule of trajectory files too
        except InputError as err:
            raise ServiceError(pb.BAD_REQUEST, str(err)) from None
        self._check_order(msg.timestamp)
        if self.live_map is not None:
            self.live_map.learner.check()  # a failed round: INTERNAL, before this frame
        t0 = time.perf_counter()
        step = self.backend.process(image, depth, camera, odom, msg.timestamp,
                                    self.depth_camera)
        if self.camera is None:
            self.camera = camera  # the default of the frames that follow
        self.last_stamp = msg.timestamp
        self.stamps_all_zero = self.stamps_all_zero and msg.timestamp == 0
        out = pb.FrameResult(index=step.index, state=STATES[step.state],
                             backend_ms=1000 * (time.perf_counter() - t0))
        if step.world_from_cam is not None:
            out.has_pose = True
            out.world_from_cam.CopyFrom(transform_msg(step.world_from_cam))
        out.events.extend(self._events(step.events))
        return out

    def _check_order(self, stamp: float) -> None:
        """A session's timestamps increase from frame to frame, or are 0 throughout (none
        given; a session whose first two frames are at 0 gives none): a frame at or before the
        last one's instant is refused, as a trajectory file's repeated instant is (one instant,
        two images: which is that instant's is not for the server to guess)."""
        last = self.last_stamp
        if last is None:
            return
        unstamped = self.stamps_all_zero  # every frame so far at 0
        if unstamped and self.n_frames >= 2 and stamp != 0:
            raise ServiceError(pb.BAD_REQUEST, f"frame.timestamp: {stamp:.17g} s after "
                               f"{self.n_frames} frames without one (0); a session gives "
                               "every frame's timestamp, or none")
        if stamp <= last + STAMP_TOLERANCE_S and not (stamp == 0 and unstamped):
            within = " (within 1 microsecond: one instant)" if stamp > last else ""
            raise ServiceError(pb.BAD_REQUEST, f"frame.timestamp: {stamp:.17g} s is not after "
                               f"the previous frame's {last:.17g} s{within} (timestamps must "
                               "increase)")

    def _events(self, events) -> list[pb.SessionEvent]:
        out = []
        for e in events:
            kind = EVENTS.get(e.kind)
            if kind is None:
                continue
            ev = pb.SessionEvent(kind=kind, frame=e.frame, reason=str(e.info.get("reason", "")),
                                 reanchor=bool(e.info.get("reanchor", False)))
            if e.world_from_cam is not None:
                ev.has_pose = True
                ev.world_from_cam.CopyFrom(transform_msg(e.world_from_cam))
            out.append(ev)
        decisions = self.plugin.stats.decisions
        for d in decisions[self._decisions_sent:]:
            out.append(pb.SessionEvent(
                kind=(pb.SessionEvent.RELOCALIZATION_ACCEPTED if d["accepted"]
                      else pb.SessionEvent.RELOCALIZATION_REJECTED),
                frame=d["frame"], num_inliers=d["num_inliers"], confidence=d["confidence"],
                reason=d["type"], position=d["position"]))
        self._decisions_sent = len(decisions)
        return out

    def train_for_save(self) -> None:
        """The first half of a save, before anything is written: a training round on the
        keyframes' current poses, waited for (as `slam --out` at its end; up to SAVE_WAIT_S
        for each of the running round and that one). It needs no worker slot nor the server's
        save lock: the round runs on the session's own learner thread, and no other message of
        this session's stream is processed meanwhile."""
        self.live_map.finish(final_round=True, timeout_s=self.SAVE_WAIT_S)

    def write(self, path) -> pb.MapSaved | None:
        """The second half: write the learned map to the folder `path` (atomically:
        `save_map`) as it stands after `train_for_save`; the session carries on. None where no
        round has published a regressor (too few rows with depth); OSError from the file
        system as it comes."""
        from slamreloc.map.meta import DatasetMeta

        live = self.live_map
        if live.save(path, DatasetMeta(kind="session", metric=True, poses="slam")) is None:
            return None
        return pb.MapSaved(num_keyframes=live.store.n_keyframes)

    def save(self, path) -> pb.MapSaved | None:
        """`train_for_save`, then `write` (the server runs them apart: only the write holds
        its save lock)."""
        self.train_for_save()
        return self.write(path)

    def cancel(self) -> None:
        """No more training for this session: a running round ends at its next step without
        publishing (a save waiting on it then finds its stream ended, or the server stopping,
        and writes nothing). Returns at once; `release` waits for the thread."""
        if self.live_map is not None:
            self.live_map.learner.stop(timeout_s=0)

    def release(self, timeout_s: float | None = None) -> None:
        """The stream ended, however it did: wait for a training round still running (its
        thread must not outlive the server: torch torn down under it aborts the process)."""
        if self.live_map is not None:
            with contextlib.suppress(Exception):  # a failed round: no one left to tell
                self.live_map.learner.wait(timeout_s)

    def close(self) -> pb.SessionClosed:
        """End of the stream: settle pending relocalizations, optimise the whole graph."""
        self.backend.finish()
        out = pb.SessionClosed(stats_json=json.dumps(self.plugin.stats.to_dict()))
        for pose in final_trajectory(self.backend):
            out.has_pose.append(pose is not None)
            out.world_from_cam.append(transform_msg(pose) if pose is not None
                                      else pb.Transform(qw=1.0))
        return out
