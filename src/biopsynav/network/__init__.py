"""Network stage: the 3D U-Net surrogate (training, export, real-time inference, Table 1).

Public API: :func:`train_case`, :func:`train`, :func:`evaluate_network_case`, :func:`evaluate`,
:class:`Surrogate`, :func:`load_for_case`, :class:`UNet3d`, :class:`UNetSpec`, :data:`PRESETS`.
Imports are lazy so that ``import biopsynav.network`` stays cheap.
"""

from __future__ import annotations

from typing import Any

_EXPORTS = {
    "train": "train", "train_case": "train", "TrainSummary": "train",
    "evaluate": "evaluate", "evaluate_network_case": "evaluate", "format_table1": "evaluate",
    "Surrogate": "infer", "load_for_case": "infer",
    "UNet3d": "unet", "UNetSpec": "unet", "PRESETS": "unet", "count_parameters": "unet",
}


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        import importlib

        return getattr(importlib.import_module(f".{_EXPORTS[name]}", __name__), name)
    raise AttributeError(name)


__all__ = list(_EXPORTS)
