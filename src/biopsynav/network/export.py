"""The deployable module (normalisation + U-Net + active mask, in mm) and its exports.

:class:`SurrogateNet` maps contact input (B, 4, nx, ny, nz) to displacement (B, 3, nx, ny, nz)
in mm: it scales the input channels by ``1 / in_scale`` (and, with quadratic features, appends
the 6 products of the scaled displacement channels divided by ``quad_scale``), runs the
U-Net, scales the output channels by ``out_scale`` and zeroes inactive nodes. Everything is
precomputed buffers, so the exported graph is the whole prediction.
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import torch
from torch import nn

from ..fileio import write_bytes_atomic
from .unet import QUADRATIC_PAIRS, UNet3d, UNetSpec


class SurrogateNet(nn.Module):
    """U-Net wrapped with its normalisation; ``forward(x mm) -> displacement mm``.

    ``in_scale`` (4,), ``out_scale`` (3,), ``quad_scale`` (6,) (quadratic features only; ones
    when None) are the per-channel scales of :mod:`biopsynav.network.data`; ``active``
    (nx, ny, nz) bool.
    """

    def __init__(self, spec: UNetSpec, in_scale: np.ndarray, out_scale: np.ndarray,
                 active: np.ndarray, quad_scale: np.ndarray | None = None) -> None:
        super().__init__()
        self.unet = UNet3d(spec)
        self.quadratic = spec.features == "quadratic"
        inv = 1.0 / np.asarray(in_scale, np.float32)
        self.register_buffer("in_inv", torch.tensor(inv).view(1, -1, 1, 1, 1))
        q = np.ones(len(QUADRATIC_PAIRS), np.float32) if quad_scale is None else quad_scale
        self.register_buffer("quad_inv", torch.tensor(1.0 / np.asarray(q, np.float32))
                             .view(1, -1, 1, 1, 1))
        self.register_buffer("quad_i", torch.tensor([i for i, _ in QUADRATIC_PAIRS]))
        self.register_buffer("quad_j", torch.tensor([j for _, j in QUADRATIC_PAIRS]))
        self.register_buffer("out_scale",
                             torch.tensor(np.asarray(out_scale, np.float32)).view(1, -1, 1, 1, 1))
        mask = torch.from_numpy(np.asarray(active, bool)).to(torch.float32)[None, None]
        self.register_buffer("mask", mask)

    def features(self, x: torch.Tensor) -> torch.Tensor:
        """The U-Net's input (B, spec.feature_channels(), nx, ny, nz) from raw input ``x``."""
        xn = x * self.in_inv
        if not self.quadratic:
            return xn
        u = xn[:, :3]
        quad = u.index_select(1, self.quad_i) * u.index_select(1, self.quad_j) * self.quad_inv
        return torch.cat([xn, quad], dim=1)

    def forward_normalised(self, x: torch.Tensor) -> torch.Tensor:
        """U-Net output in units of ``out_scale`` (before masking): used by the training loss."""
        return self.unet(self.features(x))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.unet(self.features(x)) * self.out_scale * self.mask


def save_torchscript(net: SurrogateNet, path: str | Path) -> Path:
    """Save ``net`` as scripted TorchScript (fp32, CPU) to ``path`` atomically.

    The file holds the scripted, not yet frozen module: a module frozen and passed through
    ``optimize_for_inference`` cannot be saved and loaded again (prepacked oneDNN weights), so
    :func:`biopsynav.inference.runtimes.load_torchscript` freezes and optimises it at load time.
    """
    import copy

    net = copy.deepcopy(net).float().cpu().eval()
    buf = io.BytesIO()
    with torch.no_grad():
        torch.jit.save(torch.jit.script(net), buf)
    return write_bytes_atomic(path, buf.getvalue())


def save_onnx(net: SurrogateNet, path: str | Path, node_shape: tuple[int, int, int]) -> Path:
    """Export ``net`` as a self-contained ONNX file (weights embedded; dynamic batch)."""
    import copy

    net = copy.deepcopy(net).float().cpu().eval()
    x = torch.zeros((1, net.in_inv.shape[1], *node_shape))
    buf = io.BytesIO()
    with torch.no_grad():
        torch.onnx.export(net, (x,), buf, dynamo=False, input_names=["x"], output_names=["y"],
                          dynamic_axes={"x": {0: "batch"}, "y": {0: "batch"}}, opset_version=17)
    return write_bytes_atomic(path, buf.getvalue())
