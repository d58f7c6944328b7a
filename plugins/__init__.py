"""Plugins for the mapping backend (entry-point group `slamreloc.plugins`).

`relocalization`: the core's regressor + PnP as the SLAM backend's relocalizer (kidnapped
recovery and loop closure); `gating`: when a relocalization is trusted.
"""
