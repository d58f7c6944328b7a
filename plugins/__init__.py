"""Plugins for the mapping backend (entry-point group `slamreloc.plugins`).

Empty in this release: the relocalization plugin and the pose-graph backend it serves are the
next milestone. The core relocalizer they will wrap is `slamreloc.localizer`.
"""
