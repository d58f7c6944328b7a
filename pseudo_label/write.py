"""The updated map: per-point provenance (`provenance.npz`: source and quality weight per
database row; read from the map being updated, written with the new one), the regressor update
(fine-tune or retrain) and the atomic write of NEW_MAP."""

from __future__ import annotations

import copy
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from slamreloc.pseudo_label.config import PseudoLabelConfig
from slamreloc.pseudo_label.finetune import finetune_regressor

from slamreloc.io.outputs import outputs_together, write_json
from slamreloc.map.format import LABELLED, PROVENANCE, SURFACE
from slamreloc.map.meta import MapMeta, SurfaceMeta, UpdateMeta
from slamreloc.map.write import save_map
from slamreloc.regressor.model import SceneCoordinateRegressor
from slamreloc.regressor.train import TrainConfig, train_regressor
from slamreloc.map.scene_map import MapDatabase, SceneMap
from slamreloc.map.surface import Surface


@dataclass
class PseudoLabels:
    """What registration and extension produced, before the regressor update."""

    old: SceneMap  # the map updated (its folder is kept)
    db: MapDatabase  # the map's labels + the new ones
    weights: np.ndarray  # per database row
    source: np.ndarray  # per database row: LABELLED, PSEUDO, NEW
    report: dict
    surface: Surface | None = None  # the map's surface, grown by the registered frames


def base_provenance(old: SceneMap) -> tuple[np.ndarray, np.ndarray]:
    """The map's own per-row source and weight: its provenance.npz (read and checked by the
    core) if it was itself updated, else all labelled, weight 1."""
    provenance = old.provenance
    if provenance is None:
        n = len(old.database.points)
        return np.full(n, LABELLED, np.int8), np.ones(n, np.float32)
    return provenance.source, provenance.quality


def _save(out: Path, meta: MapMeta, model, db: MapDatabase, provenance: dict,
          surface: Surface | None) -> Path:
    """The map's own atomic, locked write, with provenance.npz (and the surface) inside it."""
    extra = {PROVENANCE: provenance}
    if surface is not None:
        extra[SURFACE] = surface.to_arrays()
    return save_map(out, meta, model, db, extra=extra)


def write_updated_map(labels: PseudoLabels, out: Path,
                      config: PseudoLabelConfig = PseudoLabelConfig(),
                      progress: bool = True, report: Path | None = None
                      ) -> tuple[SceneMap, dict]:
    """Update the regressor (fine-tune or retrain) and write NEW_MAP; returns it and the
    report (with the update's stats and timing). `report`: write the report there too,
    together with the map (`outputs_together`: both new, or both as they were)."""
    out = Path(out)
    old, db, rep = labels.old, labels.db, dict(labels.report)
    rep["timings_s"] = dict(rep["timings_s"])
    map_epochs = old.info.train_config.epochs
    t0 = time.perf_counter()
    if config.update == "finetune":
        # a fresh copy of the old weights: the old map's files and object stay as they were
        model = copy.deepcopy(old.regressor)
        epochs = config.epochs or max(1, round(config.finetune_epoch_fraction * map_epochs))
        train_stats = finetune_regressor(model, db.descriptors, db.points, labels.weights,
                                         replace(config.finetune, epochs=epochs), config.device,
                                         progress)
    else:
        model = SceneCoordinateRegressor(old.regressor.config)
        # the map's own training settings, except its precision: that was resolved for the
        # machine that trained it (bf16 recorded on an AMX machine would be emulated, ~30x
        # slower, on an AVX2-only one); this machine chooses its own
        tc = replace(old.info.train_config, precision=TrainConfig.precision,
                     epochs=config.epochs or map_epochs)
        train_stats = {"mode": "retrain", **train_regressor(
            model, db.descriptors, db.points, tc, config.device, progress,
            weights=labels.weights)}
    rep["timings_s"]["update_s"] = time.perf_counter() - t0
    rep["timings_s"]["total_s"] = rep["timings_s"]["pseudo_label_s"] + rep["timings_s"]["update_s"]
    rep["update"] = train_stats
    rep["new_map"] = str(out.resolve())
    info = old.info
    history = (info.pseudo_label.history if info.pseudo_label else None) or ()
    # the datasets of the old map's own updates: the new map still holds their frames
    earlier = [] if info.pseudo_label is None else [
        *(info.pseudo_label.earlier_dataset_roots or ()),
        *([] if (root := info.recorded_inputs()["the dataset of the map's update"]) is None
          else [str(root)])]
    update = UpdateMeta(
        source_map=str(Path(old.root).resolve()), dataset=rep["dataset"],
        n_frames=rep["n_frames"], n_frames_registered=rep["n_frames_registered"],
        n_inherited_labels=rep["n_inherited_labels"],
        n_triangulated_labels=rep["n_triangulated_labels"],
        n_new_points=rep["n_new_points"], update=config.update,
        provenance=f"{PROVENANCE}: source per database row (0 labelled, 1 inherited "
                   "pseudo-label, 2 triangulated from registered frames), quality weight",
        history=(*history, str(Path(old.root).resolve())),
        earlier_dataset_roots=tuple(dict.fromkeys(earlier)) or None)
    meta = replace(
        info, labels={**info.labels, "n_labelled": int(len(db.points)),
                      "n_labelled_map": int(len(old.database.points)),
                      "n_pseudo": rep["n_inherited_labels"],
                      "n_triangulated": rep["n_triangulated_labels"]},
        train={**(info.train or {}), "update": train_stats}, pseudo_label=update,
        surface=info.surface if labels.surface is None else replace(
            info.surface or SurfaceMeta(), n_points=len(labels.surface.points)))
    with outputs_together():
        _save(out, meta, model, db, {"source": labels.source, "quality": labels.weights},
              labels.surface)
        if report is not None:
            write_json(report, rep)
    return SceneMap.load(out), rep
