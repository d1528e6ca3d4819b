"""The argument handling and pure helpers of `benchmarks/shifted_domain.py` (the benchmark itself is too slow here).

Its fine-tune mode calls `branchrange train-segmenter --coco … --images … --out BUNDLE`; these tests check what
it does before and around that call: the frame counts it accepts, what it refuses, how it finds a bundle's model.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"
sys.path.insert(0, str(BENCHMARKS))
import shifted_domain  # noqa: E402


def test_frame_counts_are_parsed_and_bad_ones_refused():
    assert shifted_domain.parse_counts("20,50,100") == [20, 50, 100]
    assert shifted_domain.parse_counts("7") == [7]
    for bad in ("", "20,x", "0", "-5,10"):
        with pytest.raises(ValueError, match="--finetune"):
            shifted_domain.parse_counts(bad)


@pytest.mark.parametrize("argv", [["--finetune", "20,fifty"], ["--finetune", "0"], ["--scenes", "1"]])
def test_bad_arguments_exit_with_a_message_before_any_work(argv, capsys):
    with pytest.raises(SystemExit) as exit_info:
        shifted_domain.main(argv)
    assert exit_info.value.code == 2
    assert "error:" in capsys.readouterr().err


def test_the_auroc_is_the_chance_a_positive_outranks_a_negative():
    assert shifted_domain.auroc([0, 1, 2], [3, 4]) == 1.0
    assert shifted_domain.auroc([3, 4], [0, 1, 2]) == 0.0
    assert shifted_domain.auroc([1, 2], [1, 3]) == pytest.approx((0.5 + 0 + 1 + 1) / 4)


def test_a_bundles_model_is_found_in_a_folder_or_taken_as_the_file(tmp_path):
    (tmp_path / "branchnet_int8.onnx").write_bytes(b"")
    with pytest.raises(FileNotFoundError, match="no ONNX model"):
        shifted_domain.bundle_model(tmp_path)
    (tmp_path / "model.onnx").write_bytes(b"")
    assert shifted_domain.bundle_model(tmp_path) == tmp_path / "model.onnx"
    assert shifted_domain.bundle_model(tmp_path / "model.onnx") == tmp_path / "model.onnx"


def test_held_out_seeds_of_each_domain_stay_apart_from_the_fine_tune_frames():
    park, orchard = shifted_domain.scene_seeds("park", 240), shifted_domain.scene_seeds("orchard", 240)
    assert park.start == 50_000 and orchard.start == shifted_domain.SHIFTED_SEED
    assert orchard.stop <= shifted_domain.FINETUNE_SEED


def test_export_only_writes_a_labelled_coco_set_and_refuses_none(tmp_path, capsys):
    pytest.importorskip("pycocotools")
    with pytest.raises(SystemExit):
        shifted_domain.main(["--export", "0", "--work", str(tmp_path)])
    assert "at least 1 frame" in capsys.readouterr().err
    assert shifted_domain.main(["--export", "1", "--work", str(tmp_path), "--cache", str(tmp_path / "cache")]) == 0
    coco = json.loads((tmp_path / "coco_1" / "annotations.json").read_text(encoding="utf-8"))
    assert [image["frame_index"] for image in coco["images"]] == [shifted_domain.FINETUNE_SEED]
    assert {a["category_id"] for a in coco["annotations"]} == {1, 2}  # branches and the trunk
