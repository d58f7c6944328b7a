"""The pseudo-label update's settings: registration, labelling, regressor update."""

from __future__ import annotations

from dataclasses import dataclass, field

from slamreloc.errors import InputError
from slamreloc.map.labels import LabelConfig
from slamreloc.pseudo_label.finetune import FinetuneConfig
from slamreloc.pseudo_label.register import RegistrationConfig
from slamreloc.registry import UPDATES


@dataclass(frozen=True)
class PseudoLabelConfig:
    rounds: int = 8  # registration + extension rounds (stops early when nothing changes)
    registration: RegistrationConfig = field(default_factory=RegistrationConfig)
    labels: LabelConfig = field(default_factory=LabelConfig)
    label_agreement_m: float = 0.05  # inherited label vs re-triangulation / depth, + 2 % depth
    depth_required: bool = True  # frames with depth: keypoints without a depth reading unlabelled
    update: str = "finetune"  # or "retrain" (from scratch, the map's own epochs)
    finetune: FinetuneConfig = field(default_factory=FinetuneConfig)
    finetune_epoch_fraction: float = 0.25  # of the map's training epochs, when epochs unset
    epochs: int | None = None  # override for the update (fine-tune or retrain)
    error_scale_px: float = 2.0  # quality weight 1 / (1 + (err / scale)^2)
    smooth: bool = True  # fuse registrations with depth odometry (where frames have depth)
    extend_surface: bool = True  # registered frames' depth joins the map's surface (new area)
    device: str = "auto"

    def __post_init__(self) -> None:
        if self.update not in UPDATES:
            raise InputError(f"`update`: unknown '{self.update}' (known: {', '.join(UPDATES)})")
        if self.rounds < 1:
            raise InputError(f"`rounds` must be at least 1, got {self.rounds}")
        if self.epochs is not None and self.epochs < 1:
            raise InputError(f"`epochs` must be at least 1, got {self.epochs}")
