"""Probe face shapes: one registry, read by case.toml, data generation, tracker and simulate."""

from __future__ import annotations

import numpy as np
import pytest

from biopsynav import footprint as fp
from biopsynav.config import config_from_dict
from biopsynav.errors import InputError


def test_shapes_cover_what_they_should():
    xy = np.array([[0.0, 0.0], [24.0, 4.0], [24.0, 0.0], [0.0, 4.9], [26.0, 0.0]])
    rect = fp.make_footprint("rectangle", (50.0, 10.0)).inside(xy)
    ellipse = fp.make_footprint("ellipse", (50.0, 10.0)).inside(xy)
    assert rect.tolist() == [True, True, True, True, False]
    assert ellipse.tolist() == [True, False, True, True, False]  # the corner is off


def test_a_registered_shape_is_a_case_toml_choice_and_reaches_every_user(monkeypatch,
                                                                         phantom_case):
    """One registration: the shape is accepted by [probe] shape and used by the tracker's
    contact set, the training patches and simulate (all through ProbeSection.footprint)."""
    from biopsynav.probe import probe_patch
    from biopsynav.simulate import patch_at
    from biopsynav.tracker.core import contact_indices

    monkeypatch.setitem(fp.FOOTPRINTS, "dot", lambda size: fp.Footprint(
        "dot", size, lambda xy: np.hypot(*xy.T) <= 3.0))
    probe = config_from_dict({"probe": {"shape": "dot"}}, "t").probe
    a = phantom_case.anatomy
    top = int(np.argmax(a.vertices[:, 2]))
    pose = np.array([[1.0, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, a.vertices[top, 2]],
                     [0, 0, 0, 1]])
    pose[:2, 3] = a.vertices[top, :2]
    dot = contact_indices(a, pose, probe.footprint, 2.0)
    wide = contact_indices(a, pose, (50.0, 10.0), 2.0)
    assert 0 < len(dot) < len(wide) and set(dot) <= set(wide)
    assert np.all(np.hypot(*(a.vertices[dot, :2] - a.vertices[top, :2]).T) <= 3.0 + 1e-9)
    patch = probe_patch(a, top, np.array([1.0, 0, 0]), probe.footprint, 5.0)
    assert set(patch) < set(probe_patch(a, top, np.array([1.0, 0, 0]), (50.0, 10.0), 5.0))
    assert len(patch_at(a, a.vertices[top], probe.footprint, 5.0).vertices) == len(patch)
    with pytest.raises(InputError, match="one of rectangle, ellipse, dot"):
        config_from_dict({"probe": {"shape": "convex"}}, "t")


def test_a_shape_without_a_nearest_point_cannot_have_rounded_edges(monkeypatch):
    """``[evaluate] p2_edge_radius_mm`` needs the shape's nearest point (the P2 reference's
    rounded body projects onto it): a registered shape without one is refused at load, with
    the key and the shape named; the built-in shapes shrink by the radius."""
    monkeypatch.setitem(fp.FOOTPRINTS, "dot", lambda size: fp.Footprint(
        "dot", size, lambda xy: np.hypot(*xy.T) <= 3.0))
    config_from_dict({"probe": {"shape": "dot"}}, "t")
    with pytest.raises(InputError, match="p2_edge_radius_mm = 2 does not fit the probe face: "
                                         "the probe shape 'dot' gives no nearest point"):
        config_from_dict({"probe": {"shape": "dot"}, "evaluate": {"p2_edge_radius_mm": 2.0}},
                         "t")
    core = fp.make_footprint("ellipse", (50.0, 10.0)).rounded_core(2.0)
    assert core.name == "ellipse" and core.size_mm == (46.0, 6.0)
