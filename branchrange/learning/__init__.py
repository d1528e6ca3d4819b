"""The segmenter's workshop: what makes, adapts and checks a BranchNet model, never run per frame.

Training on synthetic scenes (`training`, its samples `samples`), confidence calibration (`calibration`,
`depth_factor`, `heldout`), the out-of-distribution reference (`ood_reference`), int8 quantization
(`quantize`), fine-tuning on a user's COCO labels (`coco_labels`, `finetune`, `from_onnx`) and the model bundle
it writes (`bundle_writer`). The commands (`branchrange train-segmenter`) and the benchmarks import it; the
per-frame path (`branchrange.core`) never does: it only loads what this package wrote.
"""
