"""The probe protocol: patch geometry, tilt, force sharing, determinism, network input."""

from __future__ import annotations

import numpy as np
import pytest

from biopsynav.case import make_phantom_case
from biopsynav.config import ProbeSection
from biopsynav.errors import InputError
from biopsynav.grid.embedding import Embedding
from biopsynav.probe import (
    centres_near_lesion,
    contact_input,
    contact_input_operator,
    eligible_centers,
    lesion_for_sample,
    nodal_forces,
    probe_frame,
    probe_patch,
    push_for_sample,
)


@pytest.fixture(scope="module")
def case(tmp_path_factory):
    return make_phantom_case(tmp_path_factory.mktemp("probe") / "case", cell_size_mm=15.0)


@pytest.fixture(scope="module")
def pushes(case):
    probe = case.cfg.probe
    centers = eligible_centers(case.anatomy, probe.min_chest_distance_mm)
    return [push_for_sample(case.anatomy, probe, 7, i, a, centers)
            for i in range(25) for a in range(2)]


def test_frame_is_orthonormal_and_right_handed():
    normal = np.array([0.3, -0.5, 0.8])
    normal /= np.linalg.norm(normal)
    for angle in (0.0, 0.7, 2.5):
        long_axis, short_axis = probe_frame(normal, angle)
        frame = np.stack([long_axis, short_axis, normal])
        assert np.allclose(frame @ frame.T, np.eye(3), atol=1e-12)
        assert np.isclose(np.linalg.det(frame), 1.0)


def test_patch_lies_in_the_footprint_box(case, pushes):
    anatomy, probe = case.anatomy, case.cfg.probe
    half = np.array([probe.footprint_mm[0] / 2, probe.footprint_mm[1] / 2,
                     probe.depth_tolerance_mm])
    for push in pushes:
        assert push.n_contact >= probe.min_contact_points
        assert push.vertex in push.contact  # the centre is always in its own box
        rel = anatomy.vertices[push.contact] - push.center
        local = rel @ np.stack([push.long_axis, push.short_axis, push.normal]).T
        assert np.all(np.abs(local) <= half + 1e-9)
        assert np.all(anatomy.normals[push.contact] @ push.normal > 0.0)
        assert not anatomy.fixed_vertices[push.contact].any()
        # every vertex in the box facing the same way is selected
        again = probe_patch(anatomy, push.vertex, push.long_axis, probe.footprint_mm,
                            probe.depth_tolerance_mm)
        assert np.array_equal(again, push.contact)


def test_centres_keep_away_from_the_chest_wall(case, pushes):
    anatomy = case.anatomy
    for push in pushes:
        depth = -(push.center - anatomy.chest_point) @ anatomy.chest_normal
        assert depth >= case.cfg.probe.min_chest_distance_mm - 1e-9
        assert not anatomy.fixed_vertices[push.vertex]


def test_direction_tilt_and_force_bounds(case, pushes):
    probe = case.cfg.probe
    tilts = np.array([p.tilt_deg for p in pushes])
    forces = np.array([p.force_n for p in pushes])
    assert np.all(np.abs(tilts) <= probe.max_tilt_deg)
    assert np.all((forces >= 0) & (forces <= probe.f_max_n))
    assert tilts.min() < -5 and tilts.max() > 5  # both signs drawn
    for push in pushes:
        assert np.isclose(np.linalg.norm(push.direction), 1.0)
        cos = -push.direction @ push.normal
        assert cos > 0  # into the tissue
        assert np.isclose(np.degrees(np.arccos(np.clip(cos, -1, 1))), abs(push.tilt_deg),
                          atol=1e-6)


def test_total_force_is_shared_by_the_contact_points(case, pushes):
    skin = Embedding.build(case.grid, case.anatomy.vertices).matrix
    for push in pushes[:10]:
        forces = nodal_forces(skin[push.contact], push.force)
        assert forces.shape == (case.grid.n_nodes, 3)
        assert np.allclose(forces.sum(axis=0), push.force, rtol=1e-12, atol=1e-12)


def test_pushes_are_reproducible_per_index_and_attempt(case, pushes):
    probe = case.cfg.probe
    again = push_for_sample(case.anatomy, probe, 7, 3, 1)
    ref = pushes[3 * 2 + 1]
    assert again.vertex == ref.vertex and again.force_n == ref.force_n
    assert np.array_equal(again.direction, ref.direction)
    other = push_for_sample(case.anatomy, probe, 7, 3, 0)
    assert (other.vertex, other.force_n) != (ref.vertex, ref.force_n)
    assert push_for_sample(case.anatomy, probe, 8, 3, 1).force_n != ref.force_n


def test_contact_input_is_a_weighted_average_with_weight_channel(case, pushes):
    skin = Embedding.build(case.grid, case.anatomy.vertices).matrix
    push = pushes[0]
    w = skin[push.contact]
    uniform = np.tile([1.0, -2.0, 3.0], (push.n_contact, 1))
    field = contact_input(w, uniform, "average")
    weight = field[:, 3]
    assert np.isclose(weight.sum(), push.n_contact)
    touched = weight > 0
    assert np.allclose(field[touched, :3], [1.0, -2.0, 3.0])
    assert np.all(field[~touched, :3] == 0)
    varied = np.random.default_rng(5).normal(size=(push.n_contact, 3))
    field = contact_input(w, varied, "average")
    expected = np.asarray(w.T @ varied)[touched] / weight[touched, None]
    assert np.allclose(field[touched, :3], expected)


@pytest.fixture(scope="module")
def compliance(case):
    from biopsynav.contact.greens import ContactCompliance

    return ContactCompliance.from_case(case)


def test_elastic_input_moves_the_points_as_given_and_is_linear(case, pushes, compliance):
    """Point displacements of a linear-elastic field loaded on the contact nodes: the elastic
    input reproduces them (W_P U = u_P) and is the operator's linear map; the average is not
    even close on the same data."""
    skin = Embedding.build(case.grid, case.anatomy.vertices).matrix
    rng = np.random.default_rng(4)
    for push in pushes[:3]:
        w = skin[push.contact]
        op = contact_input_operator(w, "elastic", compliance)
        nodes = np.flatnonzero(op.weights > 0)
        rows, _ = compliance.contact_dofs(nodes)
        forces = rng.normal(size=len(rows))
        field = np.zeros(3 * compliance.n_nodes)
        field[compliance.out_pos] = forces @ compliance.zt[rows].astype(np.float64)
        u_nodes = field.reshape(3, -1).T
        u_p = w @ u_nodes
        got = contact_input(w, u_p, "elastic", compliance)
        assert np.allclose(got[:, 3], op.weights)
        scale = np.abs(u_p).max()
        assert np.abs(w @ got[:, :3] - u_p).max() < 1e-3 * scale
        assert np.allclose(op.field(u_p), got)
        assert np.all(got[op.weights == 0, :3] == 0)
        average = contact_input(w, u_p, "average")
        assert np.abs(w @ average[:, :3] - u_p).max() > 10 * np.abs(w @ got[:, :3] - u_p).max()


def test_elastic_input_on_springs_is_the_linear_field_of_that_contact(case, pushes, compliance):
    """With springs the input's nodal values are those of the FE model's (linear regime)
    solution with the points tied by the same springs: the points lag their targets."""
    from biopsynav.fem import FEModel, Loads, SolverSettings, solve

    model = FEModel.from_case(case)
    w = Embedding.build(case.grid, case.anatomy.vertices).matrix[pushes[0].contact]
    springs = np.linspace(0.01, 0.03, w.shape[0])  # N/mm
    # a 0.01 mm push: the linear regime (its nonlinearity about 1e-4), and a residual well
    # above the round-off floor of the decoupled law's forces (about 1e-10 of |R0| here;
    # tests/fem/test_solver.py checks a push that reaches it)
    g = np.tile([0.0, 0.0, -1e-2], (w.shape[0], 1))
    u, report = solve(model, Loads(prescribed_matrix=w, prescribed_displacement=g,
                                   prescribed_stiffness=springs),
                      SolverSettings(tol_residual=1e-9, tol_displacement=1e-9,
                                     single_precision=False))
    assert report.spring_factor == 1.0  # the springs as asked, not a fallback's
    op = contact_input_operator(w, "elastic", compliance, springs)
    fe = u.T.ravel()[op.positions]  # channel-major, as the operator writes
    got = op.matrix @ g.ravel()
    assert np.abs(got - fe).max() < 1e-3 * np.abs(fe).max()
    lag = np.abs(w @ op.field(g)[:, :3] - g).max()
    assert lag > 0.05 * 1e-2


def test_unknown_or_incomplete_contact_input_is_an_input_error(case, pushes):
    skin = Embedding.build(case.grid, case.anatomy.vertices).matrix
    w = skin[pushes[0].contact]
    with pytest.raises(InputError, match="unknown contact input"):
        contact_input_operator(w, "nearest")
    with pytest.raises(InputError, match="compliance"):
        contact_input_operator(w, "elastic", None)


def test_tilt_zero_pushes_along_the_inward_normal(case):
    probe = ProbeSection(max_tilt_deg=0.0)
    push = push_for_sample(case.anatomy, probe, 0, 0, 0)
    assert np.allclose(push.direction, -push.normal)


def test_training_force_exponent_and_scale_shape_only_training_forces(case, pushes):
    """A training push draws s f_max u^e from the same random numbers as the uniform force:
    the patch, tilt and direction stay; a held-out push (``training`` false) keeps the uniform
    force in [0, f_max] whatever the exponent and scale."""
    import dataclasses

    probe = dataclasses.replace(case.cfg.probe, train_force_exponent=0.5, train_force_scale=1.5)
    centers = eligible_centers(case.anatomy, probe.min_chest_distance_mm)
    for i, ref in enumerate(pushes[::2][:10]):
        held_out = push_for_sample(case.anatomy, probe, 7, i, 0, centers)
        trained = push_for_sample(case.anatomy, probe, 7, i, 0, centers, training=True)
        assert held_out.force_n == ref.force_n
        assert trained.vertex == ref.vertex and trained.tilt_deg == ref.tilt_deg
        assert np.array_equal(trained.direction, ref.direction)
        u = ref.force_n / probe.f_max_n
        assert np.isclose(trained.force_n, 1.5 * probe.f_max_n * np.sqrt(u), rtol=1e-12)
        assert trained.force_n >= held_out.force_n
    uniform = dataclasses.replace(probe, train_force_exponent=1.0, train_force_scale=1.0)
    assert push_for_sample(case.anatomy, uniform, 7, 4, 0, centers,
                           training=True).force_n == pushes[8].force_n


def test_training_depth_exponent_shapes_only_training_rigid_depths(case):
    """A training rigid push draws its depth as d_max u^e from the same random numbers as the
    uniform depth: the patch and direction stay, the depth is d_max (depth / d_max)^e; a
    held-out push keeps the uniform depth whatever the exponent, and a training push of e = 1
    draws the held-out push's depth to the bit."""
    import dataclasses

    from biopsynav.probe import deepest_rigid_push

    anatomy = case.anatomy
    uniform = dataclasses.replace(case.cfg.probe, rigid_share=1.0, train_depth_exponent=1.0)
    deep = dataclasses.replace(uniform, train_depth_exponent=0.5)
    centers = eligible_centers(anatomy, uniform.min_chest_distance_mm)
    depths = []
    for i in range(12):
        ref = push_for_sample(anatomy, uniform, 7, i, 0, centers, training=True)
        held_out = push_for_sample(anatomy, deep, 7, i, 0, centers)
        trained = push_for_sample(anatomy, deep, 7, i, 0, centers, training=True)
        assert held_out.push_mm == ref.push_mm > 0.0
        assert trained.vertex == ref.vertex
        assert np.array_equal(trained.direction, ref.direction)
        d_max = deepest_rigid_push(anatomy, deep, trained.contact, trained.direction)
        assert np.isclose(trained.push_mm, d_max * np.sqrt(ref.push_mm / d_max), rtol=1e-12)
        depths.append((ref.push_mm, trained.push_mm))
    ref_depths, deep_depths = np.array(depths).T
    assert np.all(deep_depths >= ref_depths) and np.any(deep_depths > ref_depths)


def test_lesion_centred_pushes_start_near_the_drawn_lesion(case, pushes):
    """``lesion_share`` 1: every push is centred within ``lesion_reach_mm`` of the skin vertex
    nearest its lesion, each lesion drawn; 0.5: about half are; 0: the pushes of before."""
    import dataclasses

    anatomy = case.anatomy
    probe = dataclasses.replace(case.cfg.probe, lesion_share=1.0, lesion_reach_mm=15.0)
    centers = eligible_centers(anatomy, probe.min_chest_distance_mm)
    skin = np.flatnonzero(anatomy.pushable)
    lesions = [lesion_for_sample(anatomy, probe, 7, i) for i in range(60)]
    assert None not in lesions and len(set(lesions)) == len(anatomy.lesions)
    for i, lesion in enumerate(lesions[:20]):
        centre = anatomy.lesions[lesion].center
        nearest = anatomy.vertices[skin[np.argmin(np.linalg.norm(anatomy.vertices[skin]
                                                                 - centre, axis=1))]]
        push = push_for_sample(anatomy, probe, 7, i, 0, centers)
        assert np.linalg.norm(push.center - nearest) <= 15.0 + 1e-9
        assert push.vertex in centers
    half = dataclasses.replace(probe, lesion_share=0.5)
    near = [lesion_for_sample(anatomy, half, 7, i) is not None for i in range(400)]
    assert 150 < sum(near) < 250
    assert all(lesion_for_sample(anatomy, case.cfg.probe, 7, i) is None for i in range(50))
    again = [push_for_sample(anatomy, case.cfg.probe, 7, i, a, centers)
             for i in range(25) for a in range(2)]
    assert [p.vertex for p in again] == [p.vertex for p in pushes]


def test_a_lesion_with_no_eligible_centre_in_reach_gets_the_nearest_one(case):
    anatomy = case.anatomy
    centers = eligible_centers(anatomy, case.cfg.probe.min_chest_distance_mm)
    near = centres_near_lesion(anatomy, centers, 0, 0.0)
    skin = np.flatnonzero(anatomy.pushable)
    nearest = skin[np.argmin(np.linalg.norm(anatomy.vertices[skin]
                                            - anatomy.lesions[0].center, axis=1))]
    dist = np.linalg.norm(anatomy.vertices[centers] - anatomy.vertices[nearest], axis=1)
    assert near.tolist() == [centers[np.argmin(dist)]]
    assert len(centres_near_lesion(anatomy, centers, 0, 1000.0)) == len(centers)
