"""Segmenters beyond the first geometric one (3D structure, ONNX models) and `make_segmenter`, which picks one by name."""
