"""Model settings that decide numerical parity with a checkpoint's source: the third hourglass's
skip (`hourglass_wiring`) and BatchNorm statistics per view in training.

The hourglass stack is checked against a functional re-implementation written here from the
published description (PSMNet's `stackhourglass.py` and OpenStereo's PSMNet cost processor), which
shares no code with `stereo.model.aggregation`: only the weights.
"""

from __future__ import annotations

import copy

import pytest
import torch
import torch.nn.functional as F

from stereo import EMCStereo
from stereo.model.aggregation import StackedHourglass


def _bn(x: torch.Tensor, state: dict[str, torch.Tensor], name: str) -> torch.Tensor:
    return F.batch_norm(
        x,
        state[f"{name}.running_mean"],
        state[f"{name}.running_var"],
        state[f"{name}.weight"],
        state[f"{name}.bias"],
        training=False,
        eps=1e-5,
    )


def _conv(
    x: torch.Tensor, state: dict[str, torch.Tensor], name: str, stride: int = 1, relu: bool = True
) -> torch.Tensor:
    """3×3×3 convolution `name.0` + BatchNorm `name.1` (+ ReLU)."""
    y = _bn(F.conv3d(x, state[f"{name}.0.weight"], stride=stride, padding=1), state, f"{name}.1")
    return F.relu(y) if relu else y


def _deconv(x: torch.Tensor, state: dict[str, torch.Tensor], name: str) -> torch.Tensor:
    y = F.conv_transpose3d(x, state[f"{name}.0.weight"], stride=2, padding=1, output_padding=1)
    return _bn(y, state, f"{name}.1")


def _hourglass(x, state, name, presqu, postsqu):
    out = _conv(x, state, f"{name}.conv1", stride=2)
    pre = _conv(out, state, f"{name}.conv2", relu=False)
    pre = F.relu(pre + postsqu) if postsqu is not None else F.relu(pre)
    out = _conv(_conv(pre, state, f"{name}.conv3", stride=2), state, f"{name}.conv4")
    post = F.relu(_deconv(out, state, f"{name}.conv5") + (presqu if presqu is not None else pre))
    return _deconv(post, state, f"{name}.conv6"), pre, post


def _classify(x, state, name):
    return F.conv3d(_conv(x, state, f"{name}.0"), state[f"{name}.1.weight"], padding=1)


def reference_stack(volume: torch.Tensor, state: dict[str, torch.Tensor], wiring: str) -> list[torch.Tensor]:
    """PSMNet's `forward` of the cost regulariser (eval mode), with the third skip chosen by `wiring`."""
    cost0 = _conv(_conv(volume, state, "dres0.0"), state, "dres0.1")
    cost0 = _conv(_conv(cost0, state, "dres1.0"), state, "dres1.1", relu=False) + cost0
    out1, pre1, post1 = _hourglass(cost0, state, "dres2", None, None)
    out1 = out1 + cost0
    out2, pre2, post2 = _hourglass(out1, state, "dres3", pre1, post1)
    out2 = out2 + cost0
    out3, _, _ = _hourglass(out2, state, "dres4", pre1 if wiring == "psmnet" else pre2, post2)
    out3 = out3 + cost0
    cost1 = _classify(out1, state, "classif1")
    cost2 = _classify(out2, state, "classif2") + cost1
    cost3 = _classify(out3, state, "classif3") + cost2
    return [cost1, cost2, cost3]


@pytest.fixture(scope="module")
def stack_weights() -> dict[str, torch.Tensor]:
    torch.manual_seed(0)
    state = StackedHourglass().state_dict()
    generator = torch.Generator().manual_seed(1)
    for key, value in state.items():  # non-trivial BatchNorm statistics, so every term matters
        if key.endswith("running_mean"):
            value.copy_(torch.rand(value.shape, generator=generator) * 0.4 - 0.2)
        elif key.endswith("running_var"):
            value.copy_(torch.rand(value.shape, generator=generator) + 0.5)
    return state


@pytest.mark.parametrize("wiring", ["psmnet", "openstereo"])
def test_each_wiring_equals_the_independent_hourglass_stack(stack_weights, wiring):
    stack = StackedHourglass(wiring)
    stack.load_state_dict(stack_weights)
    stack.eval()
    volume = torch.randn(1, 64, 8, 16, 16, generator=torch.Generator().manual_seed(2))
    with torch.no_grad():
        got = stack(volume.clone())
        expected = reference_stack(volume, stack_weights, wiring)
        other = reference_stack(volume, stack_weights, "openstereo" if wiring == "psmnet" else "psmnet")
    for g, e in zip(got, expected):
        torch.testing.assert_close(g, e, atol=1e-4, rtol=1e-4)
    # The wirings differ only in the third cost, and by far more than rounding.
    torch.testing.assert_close(got[1], other[1], atol=1e-4, rtol=1e-4)
    assert float((got[2] - other[2]).abs().max()) > 1e-2


def test_wiring_is_part_of_the_model_config_and_refuses_unknown_names():
    assert EMCStereo().config.hourglass_wiring == "openstereo"
    assert EMCStereo(hourglass_wiring="psmnet").aggregation.wiring == "psmnet"
    with pytest.raises(ValueError, match="hourglass_wiring must be one of psmnet, openstereo, got 'pre3'"):
        EMCStereo(hourglass_wiring="pre3")


def test_training_runs_the_feature_extractor_per_view_so_batchnorm_sees_one_view_at_a_time():
    """Running statistics after one training forward equal those of two per-view backbone passes."""
    torch.manual_seed(0)
    model = EMCStereo(ema=False, msf=False, coord=False, max_disp=16).train()
    reference = copy.deepcopy(model.backbone)
    left = torch.randn(1, 3, 256, 512)  # batch 1 at 512 wide: the coarsest SPP pool keeps 2 values
    right = torch.randn(1, 3, 256, 512) * 2 + 1  # different statistics per view
    model(left, right)
    with torch.no_grad():
        reference(left)
        reference(right)
    got, expected = model.backbone.state_dict(), reference.state_dict()
    for key in expected:
        if "running" in key or "num_batches" in key:
            torch.testing.assert_close(got[key], expected[key], msg=key)
    stem = "firstconv.0.1.num_batches_tracked"
    assert int(got[stem]) == 2  # two updates, one per view (one batched pass would count 1)


def test_batch_one_below_512_px_falls_back_to_both_views_together_with_a_warning(monkeypatch):
    """There a per-view pass would leave BatchNorm one value per channel (the reference fails)."""
    from stereo.model import emcstereo

    monkeypatch.setattr(emcstereo, "_FALLBACK_WARNED", [])
    torch.manual_seed(0)
    model = EMCStereo(ema=False, msf=False, coord=False, max_disp=16).train()
    pair = torch.randn(1, 3, 256, 256), torch.randn(1, 3, 256, 256)
    with pytest.warns(UserWarning, match="BatchNorm statistics span both views"):
        model(*pair)
    assert int(model.backbone.firstconv[0][1].num_batches_tracked) == 1
