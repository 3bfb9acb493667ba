"""Architecture: shapes, presets and parameter counts."""

from __future__ import annotations

import pytest
import torch

from biopsynav.errors import InputError
from biopsynav.network.unet import (
    PRESETS,
    Conv3d,
    UNet3d,
    UNetSpec,
    count_parameters,
    preset_spec,
)


def test_forward_shape_and_channels():
    spec = UNetSpec(base_channels=4, levels=3)
    net = UNet3d(spec)
    y = net(torch.zeros(2, 4, 16, 8, 8))
    assert y.shape == (2, 3, 16, 8, 8)
    assert spec.channels() == [4, 8, 16, 32]
    convs = [m for m in net.modules() if isinstance(m, torch.nn.Conv3d)]
    assert all(m.kernel_size == (3, 3, 3) and m.padding == (1, 1, 1) for m in convs[:-1])
    assert convs[-1].kernel_size == (1, 1, 1) and convs[-1].out_channels == 3
    ups = [m for m in net.modules() if isinstance(m, torch.nn.ConvTranspose3d)]
    assert len(ups) == 3 and all(m.kernel_size == (2, 2, 2) and m.stride == (2, 2, 2) for m in ups)


def test_paper_preset_about_90m_parameters_without_allocating():
    spec = PRESETS["paper"]
    assert spec.channels() == [128, 256, 512, 1024]
    assert 85e6 < count_parameters(spec) < 95e6


def test_default_preset_small():
    spec = PRESETS["default"]
    assert (spec.activation, spec.features, spec.feature_channels()) == ("silu", "quadratic", 10)
    assert count_parameters(spec) == 352_419  # 351,123 + 6 * 8 * 27 first-layer weights


def test_unknown_features_refused():
    with pytest.raises(InputError, match="\\[network\\] features"):
        preset_spec("custom", features="cubic")


@pytest.mark.parametrize("norm", ["batch", "instance", "group"])
@pytest.mark.parametrize("act", ["leaky_relu", "gelu", "silu"])
def test_custom_norm_and_activation(norm, act):
    """The network holds the norm and the activation asked for, and only those."""
    net = UNet3d(preset_spec("custom", levels=2, base_channels=4, norm=norm, activation=act))
    assert net(torch.zeros(2, 4, 8, 8, 4)).shape == (2, 3, 8, 8, 4)
    norms = {"batch": torch.nn.BatchNorm3d, "instance": torch.nn.InstanceNorm3d,
             "group": torch.nn.GroupNorm}
    acts = {"leaky_relu": torch.nn.LeakyReLU, "gelu": torch.nn.GELU, "silu": torch.nn.SiLU}
    kinds = {type(m) for m in net.modules()}
    assert norms[norm] in kinds and not (set(norms.values()) - {norms[norm]}) & kinds
    assert acts[act] in kinds and not (set(acts.values()) | {torch.nn.ReLU}) - {acts[act]} \
        & kinds


def test_bad_preset():
    with pytest.raises(InputError, match="unknown network preset"):
        preset_spec("huge")


def _uncropped_forward(net: UNet3d, x: torch.Tensor) -> torch.Tensor:
    """The forward pass of before any node count was allowed: floor pooling, no crop."""
    skips = []
    for block in net.down:
        x = block(x)
        skips.append(x)
        x = torch.nn.functional.max_pool3d(x, 2)
    x = net.bottleneck(x)
    for i, (up, dec) in enumerate(zip(net.up, net.dec, strict=True)):
        x = dec(torch.cat([up(x), skips[len(skips) - 1 - i]], dim=1))
    return net.head(x)


def test_multiples_of_two_to_the_levels_give_the_network_of_before():
    torch.manual_seed(0)
    net = UNet3d(UNetSpec(base_channels=4, levels=3)).eval()
    x = torch.randn(2, 4, 16, 8, 24)
    with torch.no_grad():
        assert torch.equal(net(x), _uncropped_forward(net, x))


@pytest.mark.parametrize("shape", [(21, 20, 15), (9, 7, 5), (2, 3, 2)])
def test_any_node_counts(shape):
    torch.manual_seed(0)
    net = UNet3d(UNetSpec(base_channels=4, levels=3)).eval()
    x = torch.randn(1, 4, *shape)
    with torch.no_grad():
        y = net(x)
        # each output node depends on the input near it: the last corner sees its own input
        x2 = x.clone()
        x2[0, :, -1, -1, -1] += 1.0
        y2 = net(x2)
    assert y.shape == (1, 3, *shape) and torch.isfinite(y).all()
    assert not torch.equal(y[0, :, -1, -1, -1], y2[0, :, -1, -1, -1])


@pytest.mark.parametrize("layout", [torch.contiguous_format, torch.channels_last_3d])
def test_a_convolution_two_nodes_deep_trains_in_fp32_under_cpu_autocast(layout):
    """oneDNN's bf16 weight gradient of a padded 3x3x3 convolution of an input two nodes deep
    read unwritten memory (another gradient each run, NaN losses now and then, on an AMD EPYC
    with AVX-512 BF16): under CPU bf16 autocast such a convolution runs in fp32, so ten runs
    give the fp32 gradient to the bit; a deeper input still runs in bf16."""
    torch.manual_seed(0)
    conv = Conv3d(64, 64, 3, padding=1).to(memory_format=layout)
    x = torch.randn(4, 64, 2, 1, 3).contiguous(memory_format=layout)

    def weight_grad(amp: bool, inp: torch.Tensor) -> tuple[torch.Tensor, torch.dtype]:
        conv.zero_grad()
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=amp):
            out = conv(inp)
        out.float().square().sum().backward()
        return conv.weight.grad.clone(), out.dtype

    ref, dtype = weight_grad(False, x)
    assert dtype == torch.float32
    for _ in range(10):
        grad, dtype = weight_grad(True, x)
        assert dtype == torch.float32 and torch.equal(grad, ref)
    assert weight_grad(True, torch.randn(4, 64, 3, 1, 3))[1] == torch.bfloat16
    scripted = torch.jit.script(conv)  # the exported model: the plain convolution
    assert torch.equal(scripted(x), conv(x))
