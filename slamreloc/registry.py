"""The names slamreloc's choices answer to, as plain data: no torch, no OpenCV, no solver.

The command line builds its choices from these (`slamreloc.cli.choices`) without importing the
pipeline, so `slamreloc --help` and an argument error answer at once; the modules that act on a
name check it against the same tuple (`slamreloc.localize.localizer.make_localizer`, ...).
"""

from __future__ import annotations

# localization methods (slamreloc.localize.localizer.make_localizer)
METHODS = ("regressor", "matching")
# compute precisions (slamreloc.runtime.precision.resolve_precision; auto: bf16 where native for
# training, on AMX CPUs and CUDA only for queries)
PRECISIONS = ("auto", "fp32", "bf16")
# training devices the command line offers (slamreloc.regressor.train.resolve_device, which
# also takes "cuda:N")
DEVICES = ("auto", "cpu", "cuda")
# the regressor's architecture presets (slamreloc.regressor.model.RegressorConfig.preset)
PRESETS: dict[str, dict] = {
    # the paper's two MLPs, plain xyz regression
    "paper": {"hidden": (512, 1024, 1024, 512)},  # ~2.3 M parameters with 256-d input
    "tiny": {"hidden": (512, 512, 512, 128)},  # ~0.7 M
    # slamreloc's default: a wide first (prototype) layer, a narrow tail and a
    # region-classification head (~1.4 M with 128-d SIFT); docs/method.md. The tail was
    # (512, 512, 128) until 0.2: as accurate, at more compute per descriptor
    "wide": {"hidden": (2048, 256, 256, 128), "head": "clusters", "n_clusters": 1024},
}
# map updates from unlabelled sequences (pseudo_label: finetune from the map's weights, or
# retrain from scratch)
UPDATES = ("finetune", "retrain")
# former presets: the configs a preset name made in earlier versions, which maps made then
# record under that name (`wide`'s tail was (512, 512, 128) until 0.2)
FORMER_PRESETS: dict[str, tuple[dict, ...]] = {
    "wide": ({"hidden": (2048, 512, 512, 128), "head": "clusters", "n_clusters": 1024},),
}
# what a map records as `dataset.kind`: the layout the readers detected
# (`slamreloc.datasets.Dataset.kind`), or "session" for a map a service session learned from
# frames sent over the wire
DATASET_KINDS = ("7scenes", "synthetic", "tum", "colmap", "rosbag", "session")
