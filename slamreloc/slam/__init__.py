"""SLAM backend: RGB-D odometry, tracking-health checks, an ISAM2 pose graph anchored in the
map frame, plugin events, and the `slamreloc slam` run with simulated kidnapping."""
