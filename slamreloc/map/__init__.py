"""The map: its folder format and metadata schema, crash-safe writing and locking, weights, labels,
surface, building and export."""
