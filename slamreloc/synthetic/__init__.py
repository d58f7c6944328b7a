"""Embedded synthetic scene: a textured room rendered by ray casting, in the 7-Scenes layout.

`render_scene(out_dir, SceneConfig(...))` writes four sequences (map, query, kidnap, unlabelled)
with RGB, z-depth (mm) and world_from_cam poses; see `writer` for the file layout.
"""

from slamreloc.synthetic.writer import SceneConfig, render_scene

__all__ = ["SceneConfig", "render_scene"]
