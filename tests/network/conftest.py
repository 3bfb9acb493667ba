"""Fixtures of the network tests: the tiny synthetic data set and its trained model come from
tests/conftest.py (the inference tests share them); ``tiny_settings`` from :mod:`.synth`."""

from __future__ import annotations

from .synth import SHAPE, tiny_settings

__all__ = ["SHAPE", "tiny_settings"]
