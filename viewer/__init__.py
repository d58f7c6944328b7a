"""The viser web viewer: `slamreloc view MAP [--trajectory T.txt ...] [--report R.json ...]`.

`load_scene_data(ViewerInputs)` reads everything (InputError on bad input), `build_scene(server,
data)` puts it on a viser server (tests call it without a browser), `serve(inputs)` runs the
viewer until Ctrl-C."""

from slamreloc.viewer.data import SceneData, ViewerInputs
from slamreloc.viewer.loaders import load_scene_data
from slamreloc.viewer.scene import SceneHandles, build_scene
from slamreloc.viewer.server import make_server, serve, start

__all__ = ["SceneData", "SceneHandles", "ViewerInputs", "build_scene", "load_scene_data",
           "make_server", "serve", "start"]
