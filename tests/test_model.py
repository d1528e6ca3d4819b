"""EMCStereo against the paper: parameter counts, state_dict layout, the stages' numerics."""

from __future__ import annotations

import itertools

import pytest
import torch
import torch.nn.functional as F

from stereo import EMCStereo
from stereo.checkpoints import ours_to_authors
from stereo.commands.params import parameter_table
from stereo.model.attention import EMA, CoordAtt, MSFBlock
from stereo.model.cost_volume import concat_cost_volume
from stereo.model.regression import upsample_cost

PAPER_COUNTS = {
    (False, False, False): 5_225_152,
    (True, False, False): 5_225_824,
    (False, True, False): 5_119_744,
    (False, False, True): 5_226_008,
    (True, True, False): 5_120_416,
    (True, False, True): 5_226_680,
    (False, True, True): 5_120_600,
    (True, True, True): 5_121_272,
}


def reference_keys(reference_docs, name: str) -> list[tuple[str, str]]:
    lines = (reference_docs / name).read_text().splitlines()
    return [tuple(line.split()) for line in lines if line.strip() and not line.startswith("#")]


@pytest.mark.parametrize("variant", list(PAPER_COUNTS))
def test_parameter_count_of_each_variant_matches_paper(variant):
    model = EMCStereo(*variant)
    assert sum(p.numel() for p in model.parameters()) == PAPER_COUNTS[variant]


def test_full_model_trainable_count_excludes_frozen_soft_argmin_weights():
    model = EMCStereo()
    assert sum(p.numel() for p in model.parameters() if p.requires_grad) == 5_121_080


def test_params_command_table_is_counted_from_code():
    table = {name: total for name, total, _, _ in parameter_table()}
    assert table == {
        "none": 5_225_152,
        "EMA": 5_225_824,
        "MSF": 5_119_744,
        "Coord": 5_226_008,
        "EMA+MSF": 5_120_416,
        "EMA+Coord": 5_226_680,
        "MSF+Coord": 5_120_600,
        "all": 5_121_272,
    }


def test_attention_module_sizes_match_paper():
    count = lambda m: sum(p.numel() for p in m.parameters())  # noqa: E731
    assert (count(EMA(128, 16)), count(MSFBlock(32)), count(CoordAtt(32, 32, 8))) == (672, 5_184, 856)


@pytest.mark.parametrize(
    ("ema", "msf", "coord", "listing"),
    [
        (True, True, True, "emcstereo_authors_state_dict.txt"),
        (False, False, False, "emcstereo_authors_noattn_state_dict.txt"),
    ],
)
def test_state_dict_in_authors_layout_matches_reference_key_for_key(reference_docs, ema, msf, coord, listing):
    expected = reference_keys(reference_docs, listing)
    ours = ours_to_authors(EMCStereo(ema, msf, coord).state_dict())
    assert [(k, str(list(v.shape)).replace(" ", "")) for k, v in ours.items()] == expected


def test_cost_volume_equals_slice_by_slice_definition():
    torch.manual_seed(0)
    left, right = torch.randn(2, 3, 4, 5, 9).unbind(0)
    volume = concat_cost_volume(left, right, 4)
    assert volume.shape == (3, 8, 4, 5, 9)
    for d in range(4):
        expected_left = left.clone()
        expected_right = torch.zeros_like(right)
        expected_left[..., :d] = 0
        expected_right[..., d:] = right[..., : 9 - d]
        torch.testing.assert_close(volume[:, :4, d], expected_left)
        torch.testing.assert_close(volume[:, 4:, d], expected_right)


def test_cost_volume_in_channels_last_layout_holds_the_same_values():
    torch.manual_seed(0)
    left, right = torch.randn(2, 1, 8, 6, 40).unbind(0)
    dense = concat_cost_volume(left, right, 12)
    channels_last = concat_cost_volume(left, right, 12, memory_format=torch.channels_last_3d)
    assert channels_last.is_contiguous(memory_format=torch.channels_last_3d)
    assert torch.equal(dense, channels_last)


def test_cost_volume_passes_gradients_to_both_features():
    left, right = torch.randn(2, 1, 4, 3, 10).unbind(0)
    left.requires_grad_(True)
    right.requires_grad_(True)
    concat_cost_volume(left, right, 5).sum().backward()
    # left[x] appears in the slices d ≤ x, right[x] in the slices d < w − x (at most 5 of each).
    expected_left = torch.arange(10).clamp(max=4).add(1).float().expand(1, 4, 3, 10)
    expected_right = (10 - torch.arange(10)).clamp(max=5).float().expand(1, 4, 3, 10)
    torch.testing.assert_close(left.grad, expected_left)
    torch.testing.assert_close(right.grad, expected_right)


@pytest.mark.parametrize("align_corners", [True, False])
def test_upsampling_equals_trilinear_over_full_range(align_corners):
    torch.manual_seed(0)
    cost = torch.randn(2, 1, 48, 8, 10)
    expected = F.interpolate(cost, size=(192, 32, 40), mode="trilinear", align_corners=align_corners)[:, 0]
    got = upsample_cost(cost, 192, 32, 40, 192, align_corners)
    torch.testing.assert_close(got, expected, atol=1e-4, rtol=1e-4)


def test_align_corners_is_a_model_setting_that_changes_the_disparity():
    """PSMNet's False and the authors' True give different maps from the same weights."""
    torch.manual_seed(0)
    cost = torch.randn(1, 1, 48, 8, 10) * 5
    authors = EMCStereo(ema=False, msf=False, coord=False)
    psmnet = EMCStereo(ema=False, msf=False, coord=False, align_corners=False)
    assert authors.config.align_corners and not psmnet.config.align_corners
    gap = (authors._upsample(cost, 192, 32, 40) - psmnet._upsample(cost, 192, 32, 40)).abs().max()
    assert float(gap) > 0.1


@pytest.fixture(scope="module")
def small_pair() -> tuple[torch.Tensor, torch.Tensor]:
    torch.manual_seed(1)
    left = torch.randn(1, 3, 256, 288)
    right = torch.roll(left, shifts=-8, dims=3)
    return left, right


def test_training_mode_returns_three_predictions_and_eval_the_third(small_pair):
    torch.manual_seed(0)
    model = EMCStereo()
    model.train()
    with torch.no_grad():  # training-mode forward (batch statistics, three heads); no graph needed here
        preds = model(*small_pair)
    assert len(preds) == 3 and all(p.shape == (1, 256, 288) for p in preds)
    model.eval()
    with torch.inference_mode():
        third = model(*small_pair)
        disparity, confidence = model.infer(*small_pair)
    assert third.shape == (1, 256, 288)
    torch.testing.assert_close(disparity, third, atol=1e-4, rtol=1e-4)
    assert float(confidence.min()) >= 0.0 and float(confidence.max()) <= 1.0
    assert float(third.min()) >= 0.0 and float(third.max()) <= 191.0


def test_range_limited_inference_stays_within_its_range(small_pair):
    model = EMCStereo(ema=False, msf=False, coord=False).eval()
    with torch.inference_mode():
        disparity, confidence = model.infer(*small_pair, max_disp=64)
    assert disparity.shape == (1, 256, 288)
    assert float(disparity.max()) <= 63.0 and float(confidence.max()) <= 1.0


@pytest.mark.parametrize("shape", [(1, 3, 250, 256), (1, 3, 224, 256), (1, 1, 256, 256)])
def test_input_that_cannot_go_through_the_network_is_refused_with_its_shape(shape):
    model = EMCStereo().eval()
    tensor = torch.zeros(shape)
    with pytest.raises(ValueError, match="×|must both be"):
        model(tensor, tensor)


def test_inference_range_must_be_multiple_of_four_within_model_range(small_pair):
    model = EMCStereo().eval()
    for bad in (0, 30, 196):
        with pytest.raises(ValueError, match="max_disp"):
            model.infer(*small_pair, max_disp=bad)


def test_eight_variants_have_distinct_key_sets():
    key_sets = {frozenset(EMCStereo(*v).state_dict()) for v in itertools.product((False, True), repeat=3)}
    assert len(key_sets) == 8


def test_a_disparity_range_the_hourglasses_cannot_halve_twice_is_refused_up_front():
    """max_disp 20 (a multiple of 4, not of 16) used to crash deep inside the hourglass; now it is a clear
    ValueError."""
    with pytest.raises(ValueError, match="multiple of 16"):
        EMCStereo(max_disp=20)
    model = EMCStereo(max_disp=32).eval()
    image = torch.zeros(1, 3, 256, 256)
    with pytest.raises(ValueError, match="multiple of 16"):
        model.infer(image, image, max_disp=20)
