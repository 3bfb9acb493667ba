"""The network engine's contact set that follows the pose (``[tracker] contact_follows_pose``):
skin the face reaches during a push joins the contact, held on the face."""

from __future__ import annotations

import copy

import numpy as np
import pytest

from biopsynav.footprint import as_footprint
from biopsynav.tracker import Tracker
from biopsynav.tracker import result as st
from biopsynav.tracker.contactset import (
    behind_face,
    onto_face,
    pinned_by_contact,
    reach_candidates,
)

TOP = np.array([[1.0, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, 75.0], [0, 0, 0, 1]])


def test_reach_candidates_keep_skin_near_the_contact_facing_the_probe():
    """Within reach of a rest contact vertex, facing the probe, pushable, not pinned and not
    in the rest contact: nothing else."""
    x = np.arange(8, dtype=float) * 10.0
    vertices = np.stack([x, np.zeros(8), np.zeros(8)], axis=1)
    normals = np.tile([0.0, 0.0, 1.0], (8, 1))
    normals[5] = [0.0, 0.0, -1.0]  # faces away from the probe
    pushable = np.ones(8, bool)
    pushable[4] = False  # chest wall or crop face
    pinned = np.zeros(8, bool)
    pinned[2] = True
    beam = np.array([0.0, 0.0, -1.0])
    got = reach_candidates(vertices, normals, pushable, beam, np.array([0]), pinned,
                           reach_mm=55.0)
    np.testing.assert_array_equal(got, [1, 3])  # 2 pinned, 4 not pushable, 5 away, 6-7 far
    assert len(reach_candidates(vertices, normals, pushable, beam, np.zeros(0, int),
                                pinned)) == 0


def test_behind_face_and_onto_face():
    """Points under the footprint beyond the tolerance behind the face plane, and their
    displacement moved onto the plane along the beam, the in-plane part kept."""
    pose = TOP.copy()
    pose[2, 3] = 50.0  # face plane z = 50, beam -z
    fp = as_footprint((50.0, 10.0))
    moved = np.array([[0.0, 0.0, 52.0],   # 2 mm behind, under the face
                      [0.0, 0.0, 50.05],  # within the tolerance
                      [0.0, 0.0, 45.0],   # in front of the face
                      [40.0, 0.0, 55.0]])  # behind, but beyond the face's end
    behind, depth = behind_face(moved, pose, fp, 0.1)
    np.testing.assert_array_equal(behind, [True, False, False, False])
    np.testing.assert_allclose(depth, [-2.0, -0.05, 5.0, -5.0])
    disp = np.array([[1.0, 2.0, -3.0]])
    held = onto_face(disp, depth[:1], pose[:3, 2])
    np.testing.assert_allclose(held, [[1.0, 2.0, -5.0]])  # 2 mm further along the beam
    assert ((moved[:1] - disp + held - pose[:3, 3]) @ pose[:3, 2])[0] == pytest.approx(0.0)


def test_pinned_by_contact_marks_cells_sharing_a_node():
    cell_nodes = np.array([[0, 1], [1, 2], [3, 4]])
    np.testing.assert_array_equal(pinned_by_contact(cell_nodes, np.array([[0, 5]]), 6),
                                  [True, False, False])
    np.testing.assert_array_equal(pinned_by_contact(cell_nodes, np.array([[1, 5]]), 6),
                                  [True, True, False])


# --- the tracker on a 10 mm phantom with a model trained briefly on linear-elastic data ---

@pytest.fixture(scope="module")
def net_case(tmp_path_factory):
    """The phantom at 10 mm cells, a small synthetic data set (the hard linear-elastic
    response plus a smooth non-linear term) and a model trained on it for a few steps."""
    from biopsynav.case import make_phantom_case
    from biopsynav.network.train import train
    from tests.network.synth import tiny_settings, write_linear_elastic_dataset

    case_dir = tmp_path_factory.mktemp("follow") / "case"
    case = make_phantom_case(case_dir, cell_size_mm=10.0)
    write_linear_elastic_dataset(case, n_train=6, n_test=2, seed=5, nodes_per_sample=6)
    train(case_dir, settings=tiny_settings(levels=2, iterations=10, val_interval=10,
                                           warmup_iterations=2, baseline="linear-elastic"),
          progress=False)
    return case


def net_tracker(case, follows: bool) -> Tracker:
    from biopsynav.case import Case
    from biopsynav.inference.surrogate import Surrogate

    cfg = copy.deepcopy(case.cfg)
    cfg.tracker.contact_follows_pose = follows
    case = Case(case.dir, cfg, case.anatomy, case.grid)
    sur = Surrogate.load(case.paths.model, case.fingerprint(), runtime="torchscript",
                         threads=1, warmup=0, case=case)
    tracker = Tracker(case, "net", surrogate=sur)
    tracker.max_contact_mm = tracker.max_probe_mm = np.inf  # a tiny envelope otherwise
    return tracker


def tilted_push(depth: float, tilt_deg: float) -> np.ndarray:
    """``TOP`` pushed ``depth`` mm down and tilted about the face's short axis, so that one
    end of the face digs into the dome."""
    a = np.radians(tilt_deg)
    rot = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    pose = TOP.copy()
    pose[:3, :3] = rot @ TOP[:3, :3]
    pose[2, 3] -= depth
    return pose


def test_the_net_engine_holds_skin_that_the_face_reaches(net_case):
    """A deep tilted push: skin not touched at rest joins the contact set, and the projected
    prediction puts it on the face plane; the hot path (point operators of the grown set)
    gives the full prediction's lesions; the rest-contact-only tracker answers otherwise."""
    follow, plain = net_tracker(net_case, True), net_tracker(net_case, False)
    for tracker in (follow, plain):
        assert tracker.set_rest_pose(TOP) > 0
    assert len(follow._reach) > 0 and len(plain._reach) == 0
    pose = tilted_push(20.0, 20.0)
    fast, full = follow.update(pose), follow.update(pose, with_surface=True)
    assert fast.status == full.status == st.OK, fast.reason
    held = follow.last_touched
    assert len(held) > 0 and not np.isin(held, follow._contact).any()
    depth = (full.surface[held] - pose[:3, 3]) @ pose[:3, 2]
    assert np.abs(depth).max() < 0.02  # on the face plane (float32 prediction)
    centres = np.array([les.displacement for les in fast.lesions])
    assert np.abs(centres - [les.displacement for les in full.lesions]).max() < 1e-4
    rest_only = plain.update(pose, with_surface=True)
    assert len(plain.last_touched) == 0
    assert ((rest_only.surface[held] - pose[:3, 3]) @ pose[:3, 2]).max() < -0.1  # in the probe
    assert np.abs(centres - [les.displacement for les in rest_only.lesions]).max() > 1e-3
    surfaces = follow.update(pose, lesion_surfaces=True)  # the grown set's lesion meshes
    assert all(les.surface is not None for les in surfaces.lesions)


def test_a_grown_contact_set_is_built_once_and_forgotten_with_the_rest_pose(net_case):
    follow = net_tracker(net_case, True)
    follow.set_rest_pose(TOP)
    pose = tilted_push(20.0, 20.0)
    first = follow.update(pose)
    grown = dict(follow._grown)
    assert len(grown) >= 1
    again = follow.update(pose)
    assert follow._grown.keys() == grown.keys()
    assert all(follow._grown[k] is grown[k] for k in grown)  # looked up, not rebuilt
    np.testing.assert_array_equal([les.center for les in first.lesions],
                                  [les.center for les in again.lesions])
    assert follow.update(TOP).status == st.OK and len(follow.last_touched) == 0
    follow.set_rest_pose(TOP)
    assert follow._grown == {}
