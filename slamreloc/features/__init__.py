"""Local features: named presets built through one factory."""

from __future__ import annotations

from slamreloc.features.base import Extractor, ExtractorConfig
from slamreloc.features.sift import Sift, SiftConfig

__all__ = ["Extractor", "ExtractorConfig", "Sift", "SiftConfig", "make_extractor", "EXTRACTORS"]

EXTRACTORS = ("sift", "superpoint")


def make_extractor(name: str, **config) -> Extractor:
    """`make_extractor("sift", max_keypoints=2048)`, `make_extractor("superpoint", weights=P)`."""
    if name == "sift":
        return Sift(**config)
    if name == "superpoint":
        from slamreloc.features.superpoint import SuperPoint

        return SuperPoint(**config)
    raise ValueError(f"unknown feature type '{name}' (known: {', '.join(EXTRACTORS)})")
