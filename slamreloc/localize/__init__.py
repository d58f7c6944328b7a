"""Localization: image -> camera pose against a map (regressor or matching), PnP, guided refinement, evaluation."""
