"""Recipes: which FE samples teach the tracking network, as case.toml values written by ``init``
and ``demo`` into a new case (``--recipe``).

A recipe is plain data: the case.toml sections and values it sets over the configuration's
defaults (the case's own ``case.toml`` then shows them, and every later stage reads them from
there like any setting). Registered in :data:`RECIPES` (:func:`register_recipe`):

* ``pushes`` (default): 450 rigid-probe pushes alone teach the tracking network from scratch
  (no force patches, no force calibration, no case network, ``[refine] samples = 0``), drawn
  as the chain's ``[refine]`` pushes are (law, places, tilts, seed); 400 trained on for 4,000
  iterations at batch 16, their depths drawn deep more often (``[probe]
  train_depth_exponent`` 0.7), 50 held out at uniform depths. Table 1 is then the tracking
  network against its teacher on those held-out pushes, not the paper's force patches.
  Measured against the independent P2 truth nearer than the chain at 20 / 30 mm pushes, in
  about a third of the time (docs/pipeline.md, "Recipes");
* ``pushes-patches``: the ``pushes`` recipe's 450 rigid-probe pushes, the very same (same
  draws, 400 trained on, 50 held out), and 270 force patches among them (240 trained on, 30
  held out), solved by one law (the pushes'), teach one tracking network from scratch
  (``[probe] rigid_share`` 0.625, the force calibrated per breast, no case network,
  ``[refine] samples = 0``; 4,000 iterations at batch 16). Table 1 is reported over both
  and for each kind (its force patches are the paper's protocol). Its network errs less
  than half as much as ``pushes``' on the paper's force patches, without reaching the
  paper's Table 1, and lies further from the truth at 30 mm on UC Davis (docs/pipeline.md,
  "Recipes");
* ``chain``: the configuration's defaults, the paper's force patches teaching a case network
  (the paper's Table 1), then ``[refine]``'s 1,000 rigid pushes training it further.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from .errors import InputError


@dataclass(frozen=True)
class Recipe:
    """A named set of case.toml values (section -> key -> value) over the defaults."""

    name: str
    summary: str
    overrides: dict[str, dict[str, Any]] = field(default_factory=dict)


#: name -> :class:`Recipe`; the choices of ``init --recipe`` and ``demo --recipe``
RECIPES: dict[str, Recipe] = {}
DEFAULT_RECIPE = "pushes"


def register_recipe(recipe: Recipe) -> None:
    """Add ``recipe`` to :data:`RECIPES` (a name already there is replaced)."""
    RECIPES[recipe.name] = recipe


def recipe_overrides(name: str) -> dict[str, dict[str, Any]]:
    """A fresh copy of recipe ``name``'s case.toml values; InputError naming the recipes
    there are for an unknown name."""
    if name not in RECIPES:
        raise InputError(f"unknown recipe {name!r}; recipes: {', '.join(sorted(RECIPES))}",
                         "--recipe")
    return {section: dict(values) for section, values in RECIPES[name].overrides.items()}


def merged(*layers: dict[str, dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """Section-wise union of case.toml value layers, a later layer's keys winning."""
    out: dict[str, dict[str, Any]] = {}
    for layer in layers:
        for section, values in layer.items():
            out.setdefault(section, {}).update(values)
    return out


#: The ``pushes`` recipe's values; ``pushes-patches`` is them with force patches among the pushes
PUSHES = {"probe": {"rigid_share": 1.0, "calibrate_force": False,
                    "train_depth_exponent": 0.7},
          "material": {"model": "neo-hookean-split-sri-inner"},
          "dataset": {"n_train": 400, "n_test": 50},
          "network": {"iterations": 4000},
          "refine": {"samples": 0}}

register_recipe(Recipe(
    "pushes", "450 rigid-probe pushes alone teach the tracking network (no force patches, no "
              "case network)", PUSHES))
register_recipe(Recipe(
    "pushes-patches", "the pushes recipe's 450 rigid-probe pushes and 270 force patches of "
                      "their law teach one tracking network (Table 1 also on its patches, "
                      "the paper's protocol; no case network)",
    merged(PUSHES, {"probe": {"rigid_share": 0.625, "calibrate_force": True},
                    "dataset": {"n_train": 640, "n_test": 80}})))
register_recipe(Recipe(
    "chain", "force patches teach a case network (the paper's Table 1), then 1,000 rigid "
             "pushes train it further ([refine]): the configuration's defaults"))
