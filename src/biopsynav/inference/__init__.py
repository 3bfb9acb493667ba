"""Deployed inference: the trained surrogate loaded from a case's model folder and run in
real time (:class:`Surrogate`), its runtimes (a registry: :func:`register_runtime`;
TorchScript and OpenVINO registered) and the checks of the model files.

Nothing here imports training code: the tracker and the OpenIGTLink service stand on it.
Imports are lazy so that the configuration can read the runtime registry cheaply.
"""

from __future__ import annotations

from typing import Any

_EXPORTS = {
    "RuntimeSpec": "runtimes", "register_runtime": "runtimes", "resolve_runtime": "runtimes",
    "Surrogate": "surrogate", "load_for_case": "surrogate",
}


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        import importlib

        return getattr(importlib.import_module(f".{_EXPORTS[name]}", __name__), name)
    raise AttributeError(name)


__all__ = list(_EXPORTS)
