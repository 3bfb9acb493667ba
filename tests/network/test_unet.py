"""Architecture: shapes, presets and parameter counts."""

from __future__ import annotations

import pytest
import torch

from biopsynav.errors import InputError
from biopsynav.network.unet import (
    PRESETS,
    UNet3d,
    UNetSpec,
    check_node_shape,
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
    net = UNet3d(preset_spec("custom", levels=2, base_channels=4, norm=norm, activation=act))
    assert net(torch.zeros(2, 4, 8, 8, 4)).shape == (2, 3, 8, 8, 4)


def test_bad_preset_and_shape():
    with pytest.raises(InputError, match="unknown network preset"):
        preset_spec("huge")
    with pytest.raises(InputError, match="multiples of 2\\^3"):
        check_node_shape((32, 24, 12), 3)
    check_node_shape((32, 24, 16), 3)
