"""Reading untrusted input within bounds, and writing files atomically: files, JSON, images, video."""
