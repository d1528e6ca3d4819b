"""The typed result: its JSON form, reading logs back, the target, and the schema generated from it."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import jsonschema
import pytest
from result_factory import branch, frame_result

from branchrange.core.frame_result import (
    SCHEMA_PATH,
    FrameResult,
    Latency,
    ResultFormatError,
    WorldTargets,
    json_schema,
)

GOLDEN_REPLAY = Path(__file__).resolve().parent / "data" / "result_v1" / "replay.jsonl"


def _golden_results() -> list[dict]:
    """The pinned replay's frame results (run header left out)."""
    return [json.loads(line) for line in GOLDEN_REPLAY.read_text(encoding="utf-8").splitlines()[1:]]


def test_the_packaged_schema_is_the_one_generated_from_the_classes():
    assert json.loads(SCHEMA_PATH.read_text(encoding="utf-8")) == json_schema(), (
        "regenerate it: python -c 'from branchrange.core.frame_result import write_json_schema; write_json_schema()'"
    )
    jsonschema.Draft202012Validator.check_schema(json_schema())


def test_the_generated_schema_accepts_real_outputs_and_refuses_broken_ones():
    validator = jsonschema.Draft202012Validator(json_schema())
    results = _golden_results()
    for result in results:
        validator.validate(result)
    too_sure = json.loads(json.dumps(results[0]))
    too_sure["branches"][0]["confidence"] = 1.5
    with pytest.raises(jsonschema.ValidationError, match="1.5 is greater than the maximum"):
        validator.validate(too_sure)
    untargeted = json.loads(json.dumps(results[0]))
    del untargeted["target_id"]
    with pytest.raises(jsonschema.ValidationError, match="'target_id' is a required property"):
        validator.validate(untargeted)


def test_a_logged_line_reads_back_typed_and_writes_back_the_same():
    for record in _golden_results():
        result = FrameResult.from_json_dict(record)
        assert isinstance(result.branches, tuple) and result.roi is not None
        assert result.to_json_dict() == record and list(result.to_json_dict()) == list(record)


def test_the_target_is_the_branch_target_id_names():
    near, far = branch(3, [0.0, 0.0, 1.0]), branch(8, [0.0, 0.0, 2.0])
    result = frame_result([near, far], target_id=8)
    assert result.target is far and result.is_target(far) and not result.is_target(near)
    assert frame_result([near, far]).target is None
    with pytest.raises(ResultFormatError, match="target_id = 5: no branch has that id"):
        frame_result([near], target_id=5)


def test_optional_parts_are_left_out_until_given_and_nulls_stay_where_the_format_has_them():
    result = frame_result([branch(1, [0.0, 0.0, 1.0])])
    written = result.to_json_dict()
    assert written["target_id"] is None and "reason" not in written and "latency" not in written
    assert list(written)[:9] == [
        "schema",
        "frame",
        "camera",
        "stereo",
        "timing_ms",
        "masks",
        "branches",
        "dropped",
        "target_id",
    ]
    daemon = replace(
        result, latency=Latency(1.0, 2.0, 3.0), targets=WorldTargets(frame="camera", target_track_id=None, tracks=())
    )
    written = daemon.to_json_dict()
    assert list(written)[-2:] == ["latency", "targets"]
    assert written["targets"] == {"frame": "camera", "target_track_id": None, "tracks": []}
    assert FrameResult.from_json_dict(written) == daemon


@pytest.mark.parametrize(
    ("change", "where"),
    [
        (lambda r: r["branches"][0].pop("distance_m"), "branches.0.distance_m"),
        (lambda r: r["frame"].update(width="wide"), "frame.width"),
        (lambda r: r.update(schema="branchrange/v0"), "schema"),
        (lambda r: r.update(extra=1), "extra"),
        (lambda r: r.update(target_id=999), "result: Value error, target_id = 999: no branch has that id"),
    ],
)
def test_a_line_that_is_not_a_v1_result_is_refused_naming_the_key(change, where):
    record = _golden_results()[0]
    change(record)
    with pytest.raises(ResultFormatError, match=rf"not a branchrange/v1 result: {where}"):
        FrameResult.from_json_dict(record)
