"""The map: its folder format, crash-safe writing and locking, weights, labels, surface, building and export."""
