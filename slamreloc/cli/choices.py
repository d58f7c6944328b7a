"""The CLI's choices, built from the registries that define them (architecture presets, feature
extractors, devices, precisions, localization methods, map-update modes, SfM matching and
mappers, serving engines): typer validates them and lists them in `--help`."""

from __future__ import annotations

from collections.abc import Iterable
from enum import Enum

from slamreloc.features import EXTRACTORS
from slamreloc.registry import DEVICES, METHODS, PRECISIONS, PRESETS, UPDATES
from slamreloc.service import ENGINES
from slamreloc.sfm import MAPPERS, MATCHING


def registry_choice(name: str, names: Iterable[str]) -> type[Enum]:
    """A str Enum whose members (name = value) are a registry's names, in its order."""
    return Enum(name, [(n, n) for n in names], type=str)


Arch = registry_choice("Arch", PRESETS)
FeatureName = registry_choice("FeatureName", EXTRACTORS)
Device = registry_choice("Device", DEVICES)
Precision = registry_choice("Precision", PRECISIONS)
Method = registry_choice("Method", METHODS)
Update = registry_choice("Update", UPDATES)
Matching = registry_choice("Matching", MATCHING)
Mapper = registry_choice("Mapper", MAPPERS)
Engine = registry_choice("Engine", ENGINES)
