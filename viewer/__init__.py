"""The viser web viewer. Empty in this release."""
