"""One probe push on the phantom through :func:`biopsynav.simulate.simulate`."""

from __future__ import annotations

import json

import numpy as np
import pytest

from biopsynav.errors import InputError
from biopsynav.fem import FEModel
from biopsynav.simulate import format_simulation, patch_at, simulate


def test_simulate_writes_surface_and_figure(phantom_case, tmp_path):
    out = tmp_path / "push"
    summary = simulate(phantom_case.dir, np.array([0.1, 0.0, -0.5]), np.array([0.0, 0.0, 76.0]),
                       out)
    for name in ("displaced_surface.vtu", "displaced_surface.stl", "simulate.png",
                 "simulate.json"):
        assert (out / name).stat().st_size > 0
    assert summary["patch_points"] > 10
    assert 0.5 < summary["max_surface_displacement_mm"] < 50
    assert json.loads((out / "simulate.json").read_text())["newton_iterations"] > 0
    assert not list(out.glob(".*.tmp"))
    text = format_simulation(summary)  # what `biopsynav simulate` prints
    assert text.startswith(f"push of (0.1, 0, -0.5) N on {summary['patch_points']} skin points")
    assert f"{summary['max_surface_displacement_mm']:.2f} mm on the skin" in text
    assert str(out) in text and "{" not in text


def test_simulate_zero_force_gives_rest_shape(phantom_case, tmp_path):
    summary = simulate(phantom_case.dir, np.zeros(3), np.array([0.0, 0.0, 76.0]), tmp_path)
    assert summary["max_surface_displacement_mm"] == 0.0


@pytest.mark.parametrize("force, at", [
    ([np.nan, 0.0, -1.0], [0.0, 0.0, 76.0]),
    ([0.0, -1.0], [0.0, 0.0, 76.0]),
    ([0.0, 0.0, -1.0], [0.0, 0.0, 200.0]),
    ([0.0, 0.0, -1.0], [np.inf, 0.0, 76.0]),
])
def test_simulate_rejects_bad_inputs(phantom_case, tmp_path, force, at):
    with pytest.raises(InputError):
        simulate(phantom_case.dir, np.array(force), np.array(at), tmp_path)


def test_probe_patch_is_oriented_box_on_the_skin(phantom_case):
    anatomy = phantom_case.anatomy
    patch = patch_at(anatomy, np.array([20.0, 10.0, 75.0]), (50.0, 10.0), 5.0)
    rel = patch.points - patch.center
    assert np.abs(rel @ patch.long_axis).max() <= 25.0 + 1e-9
    assert np.abs(rel @ patch.short_axis).max() <= 5.0 + 1e-9
    assert abs(patch.long_axis @ patch.normal) < 1e-12
    assert np.ptp(rel @ patch.long_axis) > 30.0  # the long side really is long


def test_model_from_case_maps_tissues(phantom_case):
    model = FEModel.from_case(phantom_case)
    cfg = phantom_case.cfg
    assert model.n_elements == int(phantom_case.grid.active_cells.sum())
    expected = cfg.material.tissues[cfg.material.default_tissue]["E_mpa"]
    assert np.allclose(model.E_mpa, expected)
    assert model.weight.min() >= cfg.grid.min_fraction
    assert model.material == cfg.material.model
