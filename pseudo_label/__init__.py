"""Semi-supervised map updates from unlabelled sequences. Empty in this release."""
