"""The deployable module (normalisation + U-Net + active mask, in mm) and its exports.

:class:`SurrogateNet` maps contact input (B, 4, nx, ny, nz) to displacement (B, 3, nx, ny, nz)
in mm: it scales the input channels by ``1 / in_scale``, runs the U-Net, scales the output
channels by ``out_scale`` and zeroes inactive nodes. Everything is precomputed buffers, so the
exported graph is the whole prediction.
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import torch
from torch import nn

from ..fileio import write_bytes_atomic
from .unet import UNet3d, UNetSpec


class SurrogateNet(nn.Module):
    """U-Net wrapped with its normalisation; ``forward(x mm) -> displacement mm``."""

    def __init__(self, spec: UNetSpec, in_scale: np.ndarray, out_scale: np.ndarray,
                 active: np.ndarray) -> None:
        super().__init__()
        self.unet = UNet3d(spec)
        inv = 1.0 / np.asarray(in_scale, np.float32)
        self.register_buffer("in_inv", torch.tensor(inv).view(1, -1, 1, 1, 1))
        self.register_buffer("out_scale",
                             torch.tensor(np.asarray(out_scale, np.float32)).view(1, -1, 1, 1, 1))
        mask = torch.from_numpy(np.asarray(active, bool)).to(torch.float32)[None, None]
        self.register_buffer("mask", mask)

    def forward_normalised(self, x: torch.Tensor) -> torch.Tensor:
        """U-Net output in units of ``out_scale`` (before masking): used by the training loss."""
        return self.unet(x * self.in_inv)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.unet(x * self.in_inv) * self.out_scale * self.mask


def to_torchscript(net: SurrogateNet) -> torch.jit.ScriptModule:
    """Frozen, inference-optimised TorchScript of a copy of ``net`` (fp32, CPU)."""
    import copy

    net = copy.deepcopy(net).float().cpu().eval()
    with torch.no_grad():
        scripted = torch.jit.script(net)
        return torch.jit.optimize_for_inference(torch.jit.freeze(scripted))


def save_torchscript(net: SurrogateNet, path: str | Path) -> Path:
    """Export ``net`` as frozen TorchScript to ``path`` atomically."""
    buf = io.BytesIO()
    torch.jit.save(to_torchscript(net), buf)
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
