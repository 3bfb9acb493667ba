"""The paper's evaluation (section 3): Table 1 (network) and Table 2 (TRE per lesion and
probe displacement for the network, the FE model and a rigid model), by simulation against a
ground truth (a registry, :mod:`biopsynav.reference_registry`: a finer grid of the same FE,
or an independent P2 tetrahedral FE) or from user-measured lesion positions. See
``docs/evaluation.md``.

Imports are lazy so that the configuration can read the reference registry cheaply.
"""

from __future__ import annotations

from typing import Any

_EXPORTS = {
    "evaluate_measured": "measured", "read_measured": "measured",
    "Placement": "placement", "place_probe": "placement", "place_case_probe": "placement",
    "push_depths": "placement",
    "evaluate_case": "run", "table2_markdown": "run", "table2_text": "run",
    "write_table2": "run", "run_simulation": "simulation",
    "BIN_EDGES_MM": "table", "BIN_NAMES": "table", "Record": "table", "Table": "table",
    "aggregate": "table", "bin_index": "table", "bin_name": "table",
}


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        import importlib

        return getattr(importlib.import_module(f".{_EXPORTS[name]}", __name__), name)
    raise AttributeError(name)


__all__ = sorted(_EXPORTS)
