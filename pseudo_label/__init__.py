"""Semi-supervised map updates from unlabelled sequences (pseudo-labelling, map extension)."""

from slamreloc.pseudo_label.config import PseudoLabelConfig
from slamreloc.pseudo_label.update import update_map

__all__ = ["PseudoLabelConfig", "update_map"]
