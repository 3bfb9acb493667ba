"""Network stage: training the 3D U-Net surrogate, its export and Table 1.

The deployed model is loaded and run by :mod:`biopsynav.inference`; the contact physics it
builds on (baseline, projection, Green's functions) is :mod:`biopsynav.contact`.

Public API: :func:`train_case`, :func:`train`, :func:`evaluate_network_case`, :func:`evaluate`,
:class:`UNet3d`, :class:`UNetSpec`, :data:`PRESETS`.
Imports are lazy so that ``import biopsynav.network`` stays cheap.
"""

from __future__ import annotations

from typing import Any

_EXPORTS = {
    "train": "train", "train_case": "train", "TrainSummary": "train",
    "evaluate": "evaluate", "evaluate_network_case": "evaluate", "format_table1": "evaluate",
    "UNet3d": "unet", "UNetSpec": "unet", "PRESETS": "unet", "count_parameters": "unet",
}


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        import importlib

        return getattr(importlib.import_module(f".{_EXPORTS[name]}", __name__), name)
    raise AttributeError(name)


__all__ = list(_EXPORTS)
