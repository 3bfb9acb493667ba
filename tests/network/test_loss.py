"""Masking: inactive nodes neither count nor dilute; statistics over active nodes only."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from biopsynav.network.data import load_dataset, normalisation_stats, quadratic_scale
from biopsynav.network.export import SurrogateNet
from biopsynav.network.metrics import (
    masked_loss,
    mean_dof_error_np,
    mean_norm_error,
    mean_norm_error_np,
)
from biopsynav.network.unet import QUADRATIC_PAIRS, UNetSpec

from .synth import write_synthetic_dataset


def _mask():
    m = torch.zeros(4, 4, 2, dtype=torch.bool)
    m[:2] = True
    return m


def test_masked_loss_ignores_inactive_nodes():
    torch.manual_seed(0)
    mask = _mask()
    pred, target = torch.randn(2, 3, 4, 4, 2), torch.randn(2, 3, 4, 4, 2)
    base = masked_loss(pred, target, mask, "mse")
    pred2 = pred.clone()
    pred2[:, :, ~mask] = 1e6
    assert torch.equal(masked_loss(pred2, target, mask, "mse"), base)
    expected = ((pred - target)[:, :, mask] ** 2).mean()  # mean over active values only
    assert torch.allclose(base, expected)
    l1 = masked_loss(pred, target, mask, "l1")
    assert torch.allclose(l1, (pred - target)[:, :, mask].abs().mean())


def test_norm_loss_is_the_batch_mean_of_e_in_mm():
    """The 'norm' loss on normalised values, scaled back to mm, is the paper's e (eq. 3)."""
    torch.manual_seed(1)
    mask = _mask()
    scale = torch.tensor([0.2, 0.5, 3.0])
    pred, target = torch.randn(3, 3, 4, 4, 2), torch.randn(3, 3, 4, 4, 2)
    loss = masked_loss(pred, target, mask, "norm", scale)
    mm = scale.view(1, 3, 1, 1, 1)
    e = mean_norm_error(pred * mm, target * mm, mask)  # (3,) mm
    assert torch.allclose(loss, e.mean(), rtol=1e-5)
    pred2 = pred.clone()
    pred2[:, :, ~mask] = 1e6  # inactive nodes neither count nor dilute
    assert torch.equal(masked_loss(pred2, target, mask, "norm", scale), loss)


def test_norm_loss_gradient_is_finite_where_the_error_is_zero():
    mask = _mask()
    target = torch.randn(2, 3, 4, 4, 2)
    pred = target.clone()
    pred[0, :, 0, 0, 0] += 1.0  # one node off, every other node exact
    pred.requires_grad_(True)
    masked_loss(pred, target, mask, "norm").backward()
    assert torch.isfinite(pred.grad).all()
    assert pred.grad[0, 0, 0, 0, 0] > 0 and pred.grad[1].abs().max() < 1e-5


def test_unknown_loss_is_refused():
    mask = _mask()
    with pytest.raises(ValueError, match="unknown loss"):
        masked_loss(torch.zeros(1, 3, 4, 4, 2), torch.zeros(1, 3, 4, 4, 2), mask, "huber")


def test_mean_norm_error_is_mean_over_active_nodes():
    mask = _mask()
    pred = torch.zeros(1, 3, 4, 4, 2)
    target = torch.zeros(1, 3, 4, 4, 2)
    target[0, 0][mask] = 3.0
    target[0, 1][mask] = 4.0
    target[0, 2][~mask] = 100.0  # inactive: must not count
    assert torch.allclose(mean_norm_error(pred, target, mask), torch.tensor([5.0]))
    assert np.allclose(mean_norm_error_np(pred.numpy(), target.numpy(), mask.numpy()), [5.0])
    # eq. (3) read per degree of freedom: (3 + 4 + 0) / 3 over the active nodes' components
    assert np.allclose(mean_dof_error_np(pred.numpy(), target.numpy(), mask.numpy()), [7 / 3])


def test_normalisation_stats_over_active_nodes_only(tmp_path):
    import zarr

    path = write_synthetic_dataset(tmp_path, shape=(8, 8, 8), n_train=6, n_test=2)
    ref_in, ref_out = normalisation_stats(load_dataset(tmp_path))
    g = zarr.open_group(str(path), mode="r+")
    act = g["active_nodes"][:]
    y = g["targets"][:]
    y[:, :, ~act] = 1e4  # garbage at inactive nodes
    g["targets"][:] = y
    x = g["inputs"][:]
    x[:, :3, ~act] = 1e4
    g["inputs"][:] = x
    data = load_dataset(tmp_path)
    s_in, s_out = normalisation_stats(data)
    np.testing.assert_allclose(s_in, ref_in, rtol=1e-6)
    np.testing.assert_allclose(s_out, ref_out, rtol=1e-6)
    x = data.inputs[data.train_idx]
    contact = (x[:, 3] > 0) & data.active
    manual = x.permute(1, 0, 2, 3, 4)[:, contact].pow(2).mean(dim=1).sqrt().numpy()
    np.testing.assert_allclose(s_in, manual, rtol=1e-5)
    np.testing.assert_allclose(s_out, s_in[:3])


def test_incomplete_samples_are_skipped(tmp_path):
    write_synthetic_dataset(tmp_path, shape=(8, 8, 8), n_train=6, n_test=3, not_done=(1, 7))
    data = load_dataset(tmp_path)
    assert data.train_idx.tolist() == [0, 2, 3, 4, 5]
    assert data.test_idx.tolist() == [6, 8]


def test_quadratic_scale_is_the_rms_of_products_over_contact_nodes(tmp_path):
    import zarr

    path = write_synthetic_dataset(tmp_path, shape=(8, 8, 8), n_train=6, n_test=2)
    data = load_dataset(tmp_path)
    s_in, _ = normalisation_stats(data)
    scale = quadratic_scale(data, s_in)
    x = data.inputs[data.train_idx].double()
    contact = (x[:, 3] > 0) & data.active
    u = x[:, :3].permute(1, 0, 2, 3, 4)[:, contact] / torch.from_numpy(s_in[:3]).double()[:, None]
    for k, (i, j) in enumerate(QUADRATIC_PAIRS):
        assert scale[k] == pytest.approx(float((u[i] * u[j]).pow(2).mean().sqrt()), rel=1e-5)
    g = zarr.open_group(str(path), mode="r+")
    xs = g["inputs"][:]
    xs[:, :3, ~g["active_nodes"][:]] = 1e4  # garbage at inactive nodes changes nothing
    g["inputs"][:] = xs
    np.testing.assert_allclose(quadratic_scale(load_dataset(tmp_path), s_in), scale, rtol=1e-6)


def test_surrogate_net_appends_scaled_products_of_the_displacement_channels():
    spec = UNetSpec(base_channels=2, levels=1, features="quadratic")
    in_scale, quad = np.array([2.0, 4.0, 5.0, 0.5]), np.arange(1.0, 7.0)
    net = SurrogateNet(spec, in_scale, np.ones(3), np.ones((4, 4, 2), bool), quad)
    x = torch.randn(2, 4, 4, 4, 2)
    f = net.features(x)
    xn = x / torch.tensor(in_scale, dtype=torch.float32).view(1, 4, 1, 1, 1)
    assert f.shape == (2, 10, 4, 4, 2)
    torch.testing.assert_close(f[:, :4], xn)
    for k, (i, j) in enumerate(QUADRATIC_PAIRS):
        torch.testing.assert_close(f[:, 4 + k], xn[:, i] * xn[:, j] / quad[k])
    linear = SurrogateNet(UNetSpec(base_channels=2, levels=1), in_scale, np.ones(3),
                          np.ones((4, 4, 2), bool))
    torch.testing.assert_close(linear.features(x), xn)
