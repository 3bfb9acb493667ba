"""The P2 reference's probe as a contact surface: the rounded body's signed distance and
normals, the planes its held skin slides on, and a push that keeps all skin out of it."""

from __future__ import annotations

import numpy as np
import pytest

from biopsynav.evaluate.p2 import SURFACE_TOL_MM, TetReference
from biopsynav.evaluate.p2_contact import (
    PENETRATION_TOL_MM,
    FlatFace,
    RoundedBody,
    Sliding,
    probe_surface,
    rounded_body,
)
from biopsynav.footprint import make_footprint

from .conftest import cube_reference


@pytest.mark.parametrize("shape", ["rectangle", "ellipse"])
def test_the_rounded_body_has_a_signed_distance_whose_gradient_is_its_normal(shape):
    """Points around a 50 x 10 mm body with 3 mm edges: moving a point by a small step
    changes its signed distance by the step along the normal, and a point moved to its
    nearest surface point lies on the surface with the same normal."""
    body = rounded_body(make_footprint(shape, (50.0, 10.0)), 3.0)
    rng = np.random.default_rng(0)
    local = rng.uniform([-32.0, -9.0, -8.0], [32.0, 9.0, 6.0], size=(4000, 3))
    point, normal, dist = body.closest(local)
    np.testing.assert_allclose(np.linalg.norm(normal, axis=1), 1.0)
    np.testing.assert_allclose(point + dist[:, None] * normal, local, atol=1e-9)
    keep = np.abs(dist) > 0.01  # away from the medial surface, where the gradient jumps
    step = 1e-6 * rng.normal(size=local.shape)
    change = body.closest(local + step)[2] - dist
    np.testing.assert_allclose(change[keep], np.einsum("mi,mi->m", step, normal)[keep],
                               atol=1e-11)
    again, normal_again, zero = body.closest(point)
    assert np.abs(zero).max() < 1e-9 and np.allclose(normal_again, normal)


def test_the_rounded_body_is_flat_under_its_face_round_at_its_edge_and_straight_beside():
    body = rounded_body(make_footprint("rectangle", (50.0, 10.0)), 3.0)
    local = np.array([[0.0, 0.0, 1.5],  # under the flat face
                      [0.0, 0.0, -0.5],  # inside, behind the face
                      [0.0, 5.0, 0.0],  # on the face plane at the edge: in front of the curve
                      [0.0, 8.0, -10.0]])  # beside the long side, high up
    _, normal, dist = body.closest(local)
    np.testing.assert_allclose(dist, [1.5, -0.5, 3.0 * np.sqrt(2.0) - 3.0, 3.0])
    np.testing.assert_allclose(normal[[0, 1, 3]], [[0, 0, 1], [0, 0, 1], [0, 1, 0]])
    np.testing.assert_allclose(normal[2], [0.0, np.sqrt(0.5), np.sqrt(0.5)])
    assert body.penetrating(local).tolist() == [False, True, False, False]
    assert not body.slid_off(local).any()


def test_the_probe_surface_is_flat_without_a_radius_and_refuses_one_that_does_not_fit():
    face = make_footprint("rectangle", (50.0, 10.0))
    assert isinstance(probe_surface(face, 0.0), FlatFace)
    assert isinstance(probe_surface(face, 2.0), RoundedBody)
    with pytest.raises(ValueError, match="does not fit a 50 x 10 mm face"):
        rounded_body(face, 5.0)


def test_skin_the_probe_swept_meets_the_face_that_swept_it_not_the_nearest_side():
    """A probe advancing 5 mm along its beam past skin under its rounded edge: the skin
    meets the edge where the probe's path crossed it (pushed along the beam and out), while
    its nearest point from where it ends up is on the side; skin that never entered, or
    with no known path, meets the nearest point."""
    from biopsynav.evaluate.p2_contact import meeting_points

    body = rounded_body(make_footprint("rectangle", (50.0, 10.0)), 3.0)
    came = np.array([[0.0, 4.0, 0.5], [0.0, 0.0, 0.5], [0.0, 9.0, -2.0], [0.0, 4.0, 0.5]])
    now = came - [0.0, 0.0, 5.0]  # the probe moved 5 mm forward: the skin 5 mm back
    came[3] = np.nan
    point, normal = meeting_points(body, came, now)
    # the edge's circle: centre (y, z) = (2, -3), radius 3; y = 4 meets it at z = sqrt(5) - 3
    np.testing.assert_allclose(point[0], [0.0, 4.0, np.sqrt(5.0) - 3.0], atol=1e-6)
    np.testing.assert_allclose(normal[0], [0.0, 2.0 / 3.0, np.sqrt(5.0) / 3.0], atol=1e-6)
    np.testing.assert_allclose(point[1], [0.0, 0.0, 0.0], atol=1e-6)
    np.testing.assert_allclose(point[2:], body.closest(now[2:])[0])
    assert normal[3, 1] == pytest.approx(1.0), "nearest from where it is: the side"


def test_a_flat_face_holds_skin_on_its_plane():
    """On the flat face a held node's plane is the face plane, whatever it slid on it."""
    face = np.eye(4)
    face[:3, :3] = np.diag([1.0, -1.0, -1.0])
    face[:3, 3] = [1.0, 2.0, 10.0]
    rest = np.array([[0.0, 0.0, 12.0], [3.0, 1.0, 11.0]])
    where = np.array([[0.5, 0.0, 9.0], [3.0, 4.0, 10.5]])
    slide = Sliding.on_surface(np.array([4, 7]), rest, where, face,
                               FlatFace(make_footprint("rectangle", (50.0, 10.0))))
    np.testing.assert_allclose(slide.normals, [[0, 0, -1], [0, 0, -1]])
    np.testing.assert_allclose(slide.offsets, (face[:3, 3] - rest) @ face[:3, 2])


@pytest.fixture(scope="module")
def cube() -> TetReference:
    """A 30 mm cube of 5 mm tetrahedra, its bottom face (z = -15) the chest wall."""
    return cube_reference(5.0)


def test_a_rounded_probe_keeps_the_skin_out_and_bends_it_round_its_edge(cube):
    """A 16 x 16 mm face with 4 mm edges pushed 4 mm into the top: no skin node is left
    inside the body, every held node lies on its surface, some on the curved edge, and the
    probe pushes the held skin (pulls only slightly)."""
    from biopsynav.evaluate.p2 import RELEASE_SHARE

    face = make_footprint("rectangle", (16.0, 16.0))
    body = rounded_body(face, 4.0)
    rest = np.diag([1.0, -1.0, -1.0, 1.0])
    rest[2, 3] = 15.0
    pushed = rest.copy()
    pushed[2, 3] -= 4.0
    contact = cube.contact(rest, face, 0.5, "slip")
    (centre,) = cube.push(rest, [pushed], contact, np.zeros((1, 3)), footprint=face,
                          edge_radius_mm=4.0)
    skin = cube.skin_nodes[cube.skin.pushable]
    local = (cube.nodes[skin] + cube.last[skin] - pushed[:3, 3]) @ pushed[:3, :3]
    assert body.closest(local)[2].min() >= -PENETRATION_TOL_MM
    held = (cube.nodes[cube.sliding] + cube.last[cube.sliding] - pushed[:3, 3]) @ pushed[:3, :3]
    _, normal, dist = body.closest(held)
    assert np.abs(dist).max() <= SURFACE_TOL_MM
    assert (normal[:, 2] < np.cos(np.radians(10.0))).any(), "skin held on the curved edge"
    forces = cube.forces_and_tangent(cube.last, tangent=False).reshape(-1, 3)
    push = np.einsum("mi,mi->m", forces[cube.sliding], normal @ pushed[:3, :3].T)
    free_once = np.isin(cube.sliding, cube.kept)  # let go, then passed the probe again
    assert push[~free_once].min() >= -RELEASE_SHARE * push.max()
    assert -4.0 < centre[0, 2] < -0.3


def test_newton_returns_skin_that_ran_off_a_curved_edge_to_it(cube):
    """A held node moved 1.5 mm along its tangent plane on a 4 mm edge lies 0.27 mm off the
    body; the retraction inside Newton puts it back on the surface, its new plane tangent
    there, and moves nothing on a flat face (whose plane is its surface)."""
    face = make_footprint("rectangle", (16.0, 16.0))
    body = rounded_body(face, 4.0)
    pose = np.diag([1.0, -1.0, -1.0, 1.0])
    pose[2, 3] = 15.0
    node = int(cube.skin_nodes[0])
    edge = np.array([[4.0 + 4.0 * np.sin(0.5), 0.0, -4.0 + 4.0 * np.cos(0.5)]])
    point, normal, _ = body.closest(edge)
    u = np.zeros_like(cube.nodes)
    slid = point + 1.5 * np.cross(normal, [0.0, 1.0, 0.0])
    u[node] = slid[0] @ pose[:3, :3].T + pose[:3, 3] - cube.nodes[node]
    slide = Sliding.on_surface(np.array([node]), cube.nodes[[node]], cube.nodes[[node]],
                               pose, body)
    assert cube._gap(slide.nodes, u, pose, body) > 0.5 * SURFACE_TOL_MM
    back, held = cube._retracted(u, slide, pose, body)
    local = (cube.nodes[[node]] + back[[node]] - pose[:3, 3]) @ pose[:3, :3]
    assert abs(body.closest(local)[2][0]) < 1e-9
    assert np.allclose(held.normals, body.closest(local)[1] @ pose[:3, :3].T)
    assert np.allclose(held.lift(back), 0.0, atol=1e-9)
    assert np.abs(back - u).max() > 0.2
    flat = FlatFace(face)
    on_face = u.copy()
    on_face[node] = np.array([3.0, 2.0, 0.0]) @ pose[:3, :3].T + pose[:3, 3] - cube.nodes[node]
    plane = Sliding.on_surface(np.array([node]), cube.nodes[[node]],
                               cube.nodes[[node]] + on_face[[node]], pose, flat)
    assert cube._gap(plane.nodes, on_face, pose, flat) <= 0.5 * SURFACE_TOL_MM
    assert np.allclose(cube._retracted(on_face, plane, pose, flat)[0], on_face, atol=1e-12)
