"""The segmenters (`Segmenter` in `segmenter`: the geometric one; 3D structure, learned, ONNX models) and
`make_segmenter` (`choose`), which picks one by name."""
