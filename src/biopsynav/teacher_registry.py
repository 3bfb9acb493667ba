"""The registry of the FE codes that teach the network, read by ``[dataset] teacher`` and
``[refine] teacher``.

``grid`` (built in, no builder): the immersed hexahedral FE of :mod:`biopsynav.fem`, on the
case grid or a finer one (``[dataset] teacher_refine``). Any other name maps to a builder, a
callable ``builder(case)`` or the ``"module:attribute"`` path of one, imported when first
built (the configuration reads the names from here without importing the data stage), that
returns an object whose ``solve(push)`` answers a rigid push on the case grid, (n_nodes, 3)
mm, or raises SolverError (:class:`biopsynav.dataset.converged.P2Teacher` is the built-in
``p2``), and whose class has
``check(case)`` (InputError for a case it cannot teach) and ``protocol(cfg, anatomy)`` (what
its answers depend on beside the case's anatomy and grid fingerprint, recorded in the data set's
protocol).
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from typing import Any

#: The immersed hexahedral FE, with no builder here (:func:`biopsynav.fem.teacher.build_teacher`)
GRID_TEACHER = "grid"

#: name -> builder(case), or its "module:attr" path; None for the built-in grid teacher
TEACHERS: dict[str, Callable[..., Any] | str | None] = {GRID_TEACHER: None}


def register_teacher(name: str, builder: Callable[..., Any] | str) -> None:
    """Make ``name`` a ``[dataset] teacher``: ``builder(case)`` (or its
    ``"module:attribute"`` path) returns the solver of the module docstring."""
    TEACHERS[name] = builder


def teacher_names() -> tuple[str, ...]:
    """The registered teachers: the allowed ``[dataset] teacher`` and ``[refine] teacher``."""
    return tuple(TEACHERS)


def teacher_builder(name: str) -> Callable[..., Any]:
    """The builder registered as ``name``, imported when given as a path; KeyError for the
    grid teacher (it has none) or an unknown name."""
    builder = TEACHERS[name]
    if builder is None:
        raise KeyError(f"teacher {name!r} has no builder: it is the grid FE itself")
    if isinstance(builder, str):
        module, _, attr = builder.partition(":")
        builder = getattr(importlib.import_module(module), attr)
    return builder


def builder_or_none(name: str) -> Callable[..., Any] | None:
    """The builder of teacher ``name`` (:func:`teacher_builder`), None for the grid FE."""
    return None if name == GRID_TEACHER else teacher_builder(name)


register_teacher("p2", "biopsynav.dataset.converged:P2Teacher")
