"""SLAM backend: RGB-D odometry, tracking-health checks, an ISAM2 pose graph anchored in the
map frame, plugin events, and the `slamreloc slam` run with simulated kidnapping.

    from slamreloc.slam import SlamBackend, load_plugin
    backend = SlamBackend(plugins=[load_plugin("relocalization", map_dir="maps/room")])
    result = backend.process(rgb, depth, camera, odometry_world_from_cam=my_pose)
    # depth not registered to the image: also its own camera, depth_camera=Camera(...)
"""

from slamreloc.slam.backend import BackendConfig, SlamBackend, StepResult, TrackState
from slamreloc.slam.events import Event, EventKind, available_plugins, load_plugin

__all__ = ["BackendConfig", "Event", "EventKind", "SlamBackend", "StepResult", "TrackState",
           "available_plugins", "load_plugin"]
