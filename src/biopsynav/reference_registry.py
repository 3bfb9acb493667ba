"""The registry of Table 2's ground truths, read by ``[evaluate] reference``
(:mod:`biopsynav.evaluate.references` holds the built-in ones and describes what a reference
does).

A builder is a callable ``builder(case, setup, settings)`` or the ``"module:attribute"`` path
of one, imported when first built: the configuration reads the names from here without
importing the evaluation stage.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from typing import Any

#: How the P2 reference's probe face holds the skin (``[evaluate] p2_friction``,
#: :meth:`biopsynav.evaluate.p2.TetReference.contact`): ``stick``, the skin it touches at rest
#: moves with it, as the tracker's contact points, and skin it reaches later slides on it;
#: ``slip``, all of it slides without friction (a face wet with ultrasound gel).
P2_FRICTIONS = ("stick", "slip")

#: name -> builder(case, setup, settings) of a Table 2 ground truth, or its "module:attr" path
REFERENCES: dict[str, Callable[..., Any] | str] = {}


def register_reference(name: str, builder: Callable[..., Any] | str) -> None:
    """Make ``name`` an ``[evaluate] reference``: ``builder(case, setup, settings)`` (or its
    ``"module:attribute"`` path) returns an object with ``set_rest_pose(pose) -> int``,
    ``update(pose) -> TrackingResult``, ``facts() -> dict``, ``describe() -> str`` and
    ``build_s`` (seconds spent building)."""
    REFERENCES[name] = builder


def reference_names() -> tuple[str, ...]:
    """The registered references: the allowed ``[evaluate] reference`` values."""
    return tuple(REFERENCES)


def reference_builder(name: str) -> Callable[..., Any]:
    """The builder registered as ``name``, imported when given as a path."""
    builder = REFERENCES[name]
    if isinstance(builder, str):
        module, _, attr = builder.partition(":")
        builder = getattr(importlib.import_module(module), attr)
    return builder


def chosen_reference(case: Any) -> tuple[str, str]:
    """The registered reference that ``case``'s ``[evaluate] reference`` stands for, and why
    in words: a builder with a ``choose(case) -> (name, why)`` (``auto``) chooses one for
    each case; any other is itself (no reason)."""
    name = case.cfg.evaluate.reference
    choose = getattr(reference_builder(name), "choose", None)
    return choose(case) if choose is not None else (name, "")


def build_reference(case: Any, setup: Any, settings: Any) -> Any:
    """The ``[evaluate] reference`` of ``case`` (:func:`chosen_reference`) for a Table 2 run
    of ``setup``."""
    return reference_builder(chosen_reference(case)[0])(case, setup, settings)


def check_reference(case: Any) -> None:
    """Raise InputError now when ``case``'s ``[evaluate] reference`` cannot serve it (the
    builder's ``check(case)``, where it has one): before an evaluation spends its time."""
    check = getattr(reference_builder(chosen_reference(case)[0]), "check", None)
    if check is not None:
        check(case)


register_reference("auto", "biopsynav.evaluate.stored:auto_reference")
register_reference("fine_grid", "biopsynav.evaluate.references:GridReference")
register_reference("p2", "biopsynav.evaluate.references:P2Reference")
register_reference("stored", "biopsynav.evaluate.stored:StoredTruth")
