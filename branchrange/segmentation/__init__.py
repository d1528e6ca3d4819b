"""Segmenters beyond the built-in geometric one, and `make_segmenter`, which picks one by name."""
