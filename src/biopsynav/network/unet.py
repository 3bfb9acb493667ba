"""3D U-Net of Mendizabal, Tagliabue et al. (2019), section 2.1.

Tensors are ``(B, C, nx, ny, nz)`` (see :mod:`biopsynav.grid.index`). The encoder has ``levels``
stages of two padded 3x3x3 convolutions followed by a 2x2x2 max pooling; the bottleneck has two
3x3x3 convolutions; the decoder has ``levels`` stages of a 2x2x2 transposed convolution,
concatenation with the matching encoder features (skip connection) and two padded 3x3x3
convolutions; a final 1x1x1 convolution maps to the output channels. Channels double per level
(``base_channels * 2**level``), so the paper preset (128, 3 levels) has a 1024-channel bottleneck.
Any node counts work: a pooling of an odd count keeps the last, partial window
(``ceil_mode``), and each transposed convolution's output is cropped to its skip connection's
shape, so the grid is not padded for the network (a grid whose counts are multiples of
``2**levels`` gives exactly the network of before, when they had to be).

``features = "quadratic"`` widens the first convolution by the 6 pairwise products of the three
displacement channels (built by :class:`~biopsynav.network.export.SurrogateNet`): the residual
that the network learns on top of the linear-elastic baseline is, to leading order, quadratic
in the displacement, and piecewise-linear ReLU stacks approximate products poorly
(docs/network.md).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
from torch import nn

from ..errors import InputError

NORMS = ("none", "batch", "instance", "group")
ACTIVATIONS = ("relu", "leaky_relu", "gelu", "silu")
FEATURES = ("linear", "quadratic")
#: Channel pairs (i, j), i <= j, of the quadratic input features, in channel order.
QUADRATIC_PAIRS = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))


@dataclass(frozen=True)
class UNetSpec:
    """Architecture of a :class:`UNet3d` (stored in ``meta.json``)."""

    in_channels: int = 4
    out_channels: int = 3
    base_channels: int = 8
    levels: int = 3
    norm: str = "none"
    activation: str = "relu"
    features: str = "linear"

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> UNetSpec:
        return cls(**{k: data[k] for k in cls.__dataclass_fields__ if k in data})

    def feature_channels(self) -> int:
        """Channels entering the first convolution: the raw inputs, plus the 6 products of
        the displacement channels with ``features = "quadratic"``."""
        return self.in_channels + (len(QUADRATIC_PAIRS) if self.features == "quadratic" else 0)

    def channels(self) -> list[int]:
        """Feature channels per encoder level, then the bottleneck (``levels + 1`` values)."""
        return [self.base_channels * 2**i for i in range(self.levels + 1)]


#: Named presets. ``default`` was chosen by measurement (docs/network.md): a width that predicts
#: in <= 3 ms on 2 CPU cores (wider networks trained no better in the 30-minute budget), SiLU and
#: quadratic features (lower held-out error than ReLU and the 4 raw channels). It does not yet
#: reach every accuracy target (BENCHMARKS.md).
PRESETS: dict[str, UNetSpec] = {
    "paper": UNetSpec(base_channels=128, levels=3),
    "default": UNetSpec(base_channels=8, levels=3, activation="silu", features="quadratic"),
}


def preset_spec(name: str, *, levels: int = 3, base_channels: int = 16, norm: str = "none",
                activation: str = "relu", features: str = "linear") -> UNetSpec:
    """Spec of preset ``name``; ``custom`` takes the given width, depth, norm, activation and
    input features."""
    if name == "custom":
        if features not in FEATURES:
            raise InputError(f"unknown input features {features!r}; known: "
                             f"{', '.join(FEATURES)}", "[network] features")
        return UNetSpec(base_channels=base_channels, levels=levels, norm=norm,
                        activation=activation, features=features)
    if name not in PRESETS:
        raise InputError(f"unknown network preset {name!r}; known: "
                         f"{', '.join([*PRESETS, 'custom'])}", "[network] preset")
    return PRESETS[name]


def section_spec(s) -> UNetSpec:
    """Spec of a ``[network]`` section ``s`` (:class:`~biopsynav.config.NetworkSection`): its
    preset, or with ``custom`` its width, depth, norm, activation and input features."""
    return preset_spec(s.preset, levels=s.levels, base_channels=s.base_channels, norm=s.norm,
                       activation=s.activation, features=s.features)


def _norm(kind: str, channels: int) -> nn.Module:
    if kind == "none":
        return nn.Identity()
    if kind == "batch":
        return nn.BatchNorm3d(channels)
    if kind == "instance":
        return nn.InstanceNorm3d(channels, affine=True)
    if kind == "group":
        return nn.GroupNorm(min(8, channels), channels)
    raise InputError(f"unknown norm {kind!r}; known: {', '.join(NORMS)}", "[network] norm")


def _act(kind: str) -> nn.Module:
    table = {"relu": nn.ReLU, "leaky_relu": lambda: nn.LeakyReLU(0.01), "gelu": nn.GELU,
             "silu": nn.SiLU}
    if kind not in table:
        raise InputError(f"unknown activation {kind!r}; known: {', '.join(ACTIVATIONS)}",
                         "[network] activation")
    return table[kind]()


class Conv3d(nn.Conv3d):
    """A padded 3x3x3 :class:`torch.nn.Conv3d` (the same weights and state-dict keys) that
    leaves bf16 autocast on the CPU for an input two nodes deep (``x.shape[2] == 2``) and
    convolves it in fp32: oneDNN's bf16 weight gradient of such a convolution (16 channels
    or more; channels-last from 8) reads memory it did not write, so the same step gives
    another gradient each run and now and then a NaN loss (measured in torch 2.13 on an AMD
    EPYC with AVX-512 BF16; docs/network.md, "Arithmetic"). Such inputs are the coarse levels
    of grids 5-8 or 9-16 nodes long in x; every other input is left to autocast."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if torch.jit.is_scripting():  # the exported model: fp32, no autocast
            return self._conv_forward(x, self.weight, self.bias)
        return self._autocast_forward(x)

    @torch.jit.unused
    def _autocast_forward(self, x: torch.Tensor) -> torch.Tensor:
        if torch.is_autocast_enabled("cpu") and x.shape[2] == 2:  # no shape test when traced
            with torch.autocast("cpu", enabled=False):
                return self._conv_forward(x.float(), self.weight, self.bias)
        return self._conv_forward(x, self.weight, self.bias)


def double_conv(c_in: int, c_out: int, norm: str, act: str) -> nn.Sequential:
    """Two padded 3x3x3 convolutions, each followed by the norm and the activation."""
    bias = norm in ("none", "instance")
    return nn.Sequential(
        Conv3d(c_in, c_out, 3, padding=1, bias=bias), _norm(norm, c_out), _act(act),
        Conv3d(c_out, c_out, 3, padding=1, bias=bias), _norm(norm, c_out), _act(act),
    )


class UNet3d(nn.Module):
    """The U-Net; ``forward(x (B, in, nx, ny, nz)) -> (B, out, nx, ny, nz)``."""

    def __init__(self, spec: UNetSpec) -> None:
        super().__init__()
        self.spec = spec
        ch = spec.channels()
        self.down = nn.ModuleList()
        c_prev = spec.feature_channels()
        for c in ch[:-1]:
            self.down.append(double_conv(c_prev, c, spec.norm, spec.activation))
            c_prev = c
        self.pool = nn.MaxPool3d(2, ceil_mode=True)
        self.bottleneck = double_conv(ch[-2], ch[-1], spec.norm, spec.activation)
        self.up = nn.ModuleList()
        self.dec = nn.ModuleList()
        for lvl in reversed(range(spec.levels)):
            self.up.append(nn.ConvTranspose3d(ch[lvl + 1], ch[lvl], 2, stride=2))
            self.dec.append(double_conv(2 * ch[lvl], ch[lvl], spec.norm, spec.activation))
        self.head = nn.Conv3d(ch[0], spec.out_channels, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        skips: list[torch.Tensor] = []
        for block in self.down:
            x = block(x)
            skips.append(x)
            x = self.pool(x)
        x = self.bottleneck(x)
        for i, (up, dec) in enumerate(zip(self.up, self.dec, strict=True)):
            skip = skips[len(skips) - 1 - i]
            x = up(x)[:, :, :skip.shape[2], :skip.shape[3], :skip.shape[4]]
            x = dec(torch.cat([x, skip], dim=1))
        return self.head(x)


def count_parameters(spec: UNetSpec) -> int:
    """Trainable parameters of ``spec`` without allocating its weights (meta device)."""
    with torch.device("meta"):
        model = UNet3d(spec)
    return sum(p.numel() for p in model.parameters())

