"""Rigid-probe training pushes (``[probe] rigid_share``): the skin under the face at rest moves
with the face, the kind is fixed per sample, and force patches stay what they were."""

from __future__ import annotations

import json

import numpy as np
import pytest
import zarr
from dataset_helpers import N_TEST, N_TRAIN, edit_config

from biopsynav.case import Case
from biopsynav.config import config_from_dict
from biopsynav.contact.constraints import grid_springs, vertex_areas
from biopsynav.contact.springs import case_young_moduli
from biopsynav.dataset.contacts import sample_contact_matrices
from biopsynav.dataset.generate import generate_case
from biopsynav.dataset.store import (
    FORCE_PATCH_KEYS,
    protocol_dict,
    protocol_fingerprint,
    same_protocol,
)
from biopsynav.errors import InputError
from biopsynav.grid.embedding import surface_embedding
from biopsynav.grid.index import tensor_to_field
from biopsynav.probe import (
    contact_input,
    eligible_centers,
    is_rigid_sample,
    pinned_skin,
    push_for_sample,
)


def compliance(case: Case):
    from biopsynav.contact.greens import ContactCompliance

    return ContactCompliance.from_case(case)


@pytest.fixture(scope="module")
def mixed(base_case, tmp_path_factory):
    """The coarse phantom with half of its samples pushed by the rigid face, generated."""
    import shutil

    dst = tmp_path_factory.mktemp("rigid") / "case"
    shutil.copytree(base_case, dst)
    edit_config(dst, probe={"rigid_share": 0.5})
    generate_case(dst, workers=1, progress=False)
    return dst


def rigid_indices(case: Case) -> list[int]:
    return [i for i in range(N_TRAIN + N_TEST) if is_rigid_sample(case.cfg.probe, i)]


def test_a_rigid_sample_moves_its_contact_with_the_face(mixed):
    """Every contact point of a rigid sample follows the face through its spring (elastic
    contact, the default): it moves along the drawn direction, lagging the face by less than
    the push; the sample's input is the linear field of the face's own motion on the same
    springs and its probe displacement the face's (what the tracker sees); the points come
    from the rest contact of the tracker: within contact_tolerance_mm of the face, never
    pinned skin."""
    case = Case.load(mixed)
    data = zarr.open_group(str(mixed / "dataset.zarr"), mode="r")
    done = np.flatnonzero(data["done"][:])
    rigid = [i for i in rigid_indices(case) if i in done]
    assert 0 < len(rigid) < len(done)  # a mix
    summary = json.loads(case.paths.dataset_summary.read_text())
    assert summary["rigid_pushes"] == len(rigid)
    skin = surface_embedding(case.grid, case.anatomy)
    pinned = pinned_skin(case.grid.fixed_nodes, skin.nodes)
    contacts = sample_contact_matrices(case, mixed, np.array(rigid))
    tol = case.cfg.solver.constraint_tolerance_mm
    for i, w in zip(rigid, contacts, strict=True):
        push = push_for_sample(case.anatomy, case.cfg.probe, case.cfg.dataset.seed, i,
                               int(data["attempt"][i]), pinned=pinned)
        assert push.rigid and push.force_n == 0.0
        assert 0.0 < push.push_mm <= case.cfg.probe.max_push_mm
        assert abs(push.tilt_deg) <= case.cfg.probe.rigid_max_tilt_deg
        assert not pinned[push.contact].any()
        local = (case.anatomy.vertices[push.contact] - push.center) @ push.normal
        assert np.all(np.abs(local) <= case.cfg.probe.contact_tolerance_mm + 1e-9)
        u = tensor_to_field(np.asarray(data["targets"][i]))
        moved = w @ u
        lag = np.linalg.norm(moved - push.displacement, axis=1)
        assert np.all(moved @ push.displacement > 0) and lag.max() < push.push_mm
        assert lag.max() > 10 * tol  # springs, not constraints
        assert data["probe_disp_mm"][i] == pytest.approx(push.push_mm, rel=1e-9)
        face = np.broadcast_to(push.displacement, moved.shape)
        inputs = tensor_to_field(np.asarray(data["inputs"][i]))
        springs = grid_springs(case.cfg.tracker.contact_stiffness, case_young_moduli(case),
                               case.grid, skin.cells[push.contact],
                               vertex_areas(case.anatomy.vertices,
                                            case.anatomy.faces)[push.contact])
        expected = contact_input(w, face, case.cfg.dataset.contact_input, compliance(case),
                                 springs)
        np.testing.assert_allclose(inputs[:, :3], expected[:, :3], atol=1e-4)


def test_the_kinds_interleave_at_fixed_places_and_one_kind_keeps_its_protocol(base_case):
    """Any first n samples hold floor(n share) rigid pushes; a mixed set's k-th rigid push is
    push k of rigid pushes alone, its force patches draws of their own; a share of 0 or 1
    fingerprints as before mixed sets existed."""
    case = Case.load(base_case)
    probe = case.cfg.probe
    centers = eligible_centers(case.anatomy, probe.min_chest_distance_mm)
    patches = [push_for_sample(case.anatomy, probe, 0, i, 0, centers) for i in range(6)]
    fp_before = protocol_fingerprint(protocol_dict(case.cfg, N_TRAIN, N_TEST))
    assert not any(p.rigid for p in patches)
    probe.rigid_share = 1.0
    pushes = [push_for_sample(case.anatomy, probe, 0, i, 0, centers) for i in range(6)]
    probe.rigid_share = 0.4
    kinds = [is_rigid_sample(probe, i) for i in range(200)]
    assert all(sum(kinds[:n]) == int(0.4 * n + 1e-9) for n in range(201))
    mixed = [push_for_sample(case.anatomy, probe, 0, i, 0, centers) for i in range(15)]
    rigid = [p for p in mixed if p.rigid]
    assert [p.rigid for p in mixed] == kinds[:15] and len(rigid) == 6
    for a, b in zip(rigid, pushes, strict=True):
        assert a.vertex == b.vertex and a.push_mm == b.push_mm
    own = [p for p in mixed if not p.rigid][:6]  # not the force patches of share 0
    same = [a.vertex == b.vertex and a.force_n == b.force_n
            for a, b in zip(own, patches, strict=True)]
    assert sum(same) < 3
    assert protocol_fingerprint(protocol_dict(case.cfg, N_TRAIN, N_TEST)) != fp_before
    probe.rigid_share = 0.0
    assert protocol_fingerprint(protocol_dict(case.cfg, N_TRAIN, N_TEST)) == fp_before


def test_a_rigid_push_compresses_the_tissue_before_the_chest_wall_by_the_share_at_most(
        base_case):
    """``[probe] max_chest_compression``: a rigid push moves the face towards the chest wall by
    at most that share of the tissue under it; a draw within the limit is the draw of before,
    a deeper one the same line shallower; force patches and their protocol stay as they were;
    0 is the protocol of rigid pushes from before the key."""
    from biopsynav.probe import chest_distance, towards_chest

    case = Case.load(base_case)
    probe = case.cfg.probe
    centers = eligible_centers(case.anatomy, probe.min_chest_distance_mm)
    fp_patches = protocol_fingerprint(protocol_dict(case.cfg, N_TRAIN, N_TEST))
    probe.max_chest_compression = 0.1
    assert protocol_fingerprint(protocol_dict(case.cfg, N_TRAIN, N_TEST)) == fp_patches
    probe.rigid_share = 1.0

    def draws(share: float) -> list:
        probe.max_chest_compression = share
        return [push_for_sample(case.anatomy, probe, 0, i, 0, centers) for i in range(40)]

    free, limited = draws(0.0), draws(0.3)
    fp = {}
    for share in (0.0, 0.3):
        probe.max_chest_compression = share
        fp[share] = protocol_fingerprint(protocol_dict(case.cfg, N_TRAIN, N_TEST))
    shallower = 0
    for a, b in zip(free, limited, strict=True):
        assert a.vertex == b.vertex and np.allclose(a.direction, b.direction)
        share = towards_chest(case.anatomy, b.displacement) / chest_distance(case.anatomy,
                                                                             b.contact)
        assert share <= 0.3 + 1e-9
        depth_a, depth_b = np.linalg.norm(a.displacement), np.linalg.norm(b.displacement)
        if depth_b < depth_a - 1e-9:  # the same random number on a shorter range
            shallower += 1
            unit = towards_chest(case.anatomy, b.direction)
            allowed = 0.3 * chest_distance(case.anatomy, b.contact) / unit
            assert allowed < probe.max_push_mm  # only where the limit bites
            assert depth_b / depth_a == pytest.approx(allowed / probe.max_push_mm)
        else:
            assert depth_b == pytest.approx(depth_a)
    assert 5 < shallower < 40
    assert fp[0.0] != fp[0.3]
    probe.max_chest_compression = 0.0
    assert "max_chest_compression" not in protocol_dict(case.cfg, N_TRAIN, N_TEST)["probe"]


def test_a_data_set_of_rigid_pushes_alone_does_not_depend_on_the_force_range(base_case):
    """With every push rigid (a [refine] data set) the force patches' keys leave the
    protocol: a new force range keeps the data set; a store that recorded them (made before)
    is still the same protocol; a mixed set keeps them."""
    cfg = Case.load(base_case).cfg
    cfg.probe.rigid_share = 1.0
    protocol = protocol_dict(cfg, N_TRAIN, N_TEST)
    assert not set(FORCE_PATCH_KEYS) & set(protocol["probe"])
    cfg.probe.f_max_n, cfg.probe.max_tilt_deg, cfg.probe.calibrate_force = 1.5, 10.0, False
    assert protocol_dict(cfg, N_TRAIN, N_TEST) == protocol
    before = {**protocol, "probe": {**protocol["probe"], "f_max_n": 4.0, "max_tilt_deg": 45.0,
                                    "calibrate_force": True, "depth_tolerance_mm": 5.0}}
    attrs = {"protocol": before, "protocol_fingerprint": protocol_fingerprint(before)}
    assert same_protocol(attrs, protocol)
    cfg.probe.rigid_max_tilt_deg = 20.0  # a key the rigid pushes use
    assert not same_protocol(attrs, protocol_dict(cfg, N_TRAIN, N_TEST))
    cfg.probe.rigid_share = 0.5
    mixed = protocol_dict(cfg, N_TRAIN, N_TEST)
    assert mixed["probe"]["f_max_n"] == 1.5
    cfg.probe.f_max_n = 2.0
    assert protocol_dict(cfg, N_TRAIN, N_TEST) != mixed
    damaged = {"protocol": "not a protocol", "protocol_fingerprint": "0" * 64}
    assert not same_protocol(damaged, mixed)  # a damaged record is another protocol


def test_rigid_pushes_need_a_depth_range():
    with pytest.raises(InputError, match="max_push_mm"):
        config_from_dict({"probe": {"rigid_share": 0.5, "max_push_mm": 0.0}})
    with pytest.raises(InputError, match="rigid_share"):
        config_from_dict({"probe": {"rigid_share": 1.5}})


def test_a_model_taught_by_force_patches_still_loads_in_a_case_that_asks_for_rigid_pushes(
        trained_case, tmp_path):
    """Rigid pushes change the data set's protocol, not the anatomy or grid: a model trained
    before (force patches only) loads as it is, and says what taught it."""
    import shutil

    from biopsynav.tracker import Tracker

    case_dir = tmp_path / "case"
    shutil.copytree(trained_case, case_dir)
    edit_config(case_dir, probe={"rigid_share": 0.5})
    tracker = Tracker.load(case_dir, engine="net")
    assert tracker.engine == "net"
    meta = json.loads(Case.load(case_dir).paths.model_meta.read_text())
    assert meta["teacher"]["rigid_share"] == 0.0


def test_a_data_sets_elastic_push_gives_its_springs_a_short_budget_and_no_points_met():
    """Data generation's rigid pushes: the springs as asked get ``[dataset] newton_budget``,
    their one fallback 4x springs gets the rigid budget, both in single precision where
    ``[solver] single_precision`` is on; never the points met (the dragging teacher)."""
    from types import SimpleNamespace

    from biopsynav.dataset.worker import RIGID_BUDGET_FACTOR, rigid_push_settings
    from biopsynav.fem import SolverSettings

    for single in (True, False):
        ctx = SimpleNamespace(settings=SolverSettings(max_total_iterations=40,
                                                      single_precision=single))
        settings = rigid_push_settings(ctx)
        assert settings.first_attempt_budget == 40
        assert settings.max_total_iterations == RIGID_BUDGET_FACTOR * 40
        assert settings.spring_fallback == (4.0,)
        assert all(np.isfinite(settings.spring_fallback))
        assert settings.elastic_single_precision is single
    assert SolverSettings().elastic_single_precision is False  # the tracker's: double


def test_pushes_near_lesions_enter_the_protocol_only_when_drawn(base_case):
    """``lesion_share`` 0 leaves both lesion keys out (every data set of before keeps its
    protocol); a share above 0 records it and the reach."""
    cfg = Case.load(base_case).cfg
    before = protocol_dict(cfg, N_TRAIN, N_TEST)
    assert not {"lesion_share", "lesion_reach_mm"} & set(before["probe"])
    cfg.probe.lesion_reach_mm = 30.0
    assert protocol_dict(cfg, N_TRAIN, N_TEST) == before
    cfg.probe.lesion_share = 0.5
    probe = protocol_dict(cfg, N_TRAIN, N_TEST)["probe"]
    assert (probe["lesion_share"], probe["lesion_reach_mm"]) == (0.5, 30.0)


def test_the_training_depth_exponent_enters_the_protocol_only_when_it_shapes_rigid_pushes(
        base_case):
    """``train_depth_exponent`` 1 (uniform depths) leaves the protocol as it was; another
    value is recorded where there are rigid pushes and left out where there are none."""
    cfg = Case.load(base_case).cfg
    cfg.probe.rigid_share = 1.0
    uniform = protocol_dict(cfg, N_TRAIN, N_TEST)
    assert "train_depth_exponent" not in uniform["probe"]
    cfg.probe.train_depth_exponent = 0.5
    deep = protocol_dict(cfg, N_TRAIN, N_TEST)
    assert deep["probe"]["train_depth_exponent"] == 0.5
    assert protocol_fingerprint(deep) != protocol_fingerprint(uniform)
    # a data set of uniform depths is another protocol for a case asking deeper pushes
    attrs = {"protocol": uniform, "protocol_fingerprint": protocol_fingerprint(uniform)}
    assert not same_protocol(attrs, deep)
    cfg.probe.rigid_share = 0.0
    assert "train_depth_exponent" not in protocol_dict(cfg, N_TRAIN, N_TEST)["probe"]


def test_pushes_near_lesions_of_a_case_without_lesions_are_refused_before_a_store(base_case,
                                                                                  tmp_path):
    """``lesion_share`` > 0 on a case with no lesions stops ``generate`` at its preflight with
    one line naming the key, before a data set exists (else every push would be centred
    anywhere without a word)."""
    import dataclasses

    case = Case.load(base_case)
    bare = Case(tmp_path, dataclasses.replace(case.cfg), dataclasses.replace(case.anatomy,
                                                                            lesions=[]),
                case.grid)
    bare.cfg.probe = dataclasses.replace(case.cfg.probe, lesion_share=0.5)
    with pytest.raises(InputError, match=r"\[probe\] lesion_share.*no lesions"):
        generate_case(bare, workers=1, progress=False)
    assert not (tmp_path / "dataset.zarr").exists()


def test_the_envelope_holds_the_compression_its_rigid_pushes_were_drawn_with():
    """A model's envelope names ``max_chest_compression`` only when its data set holds rigid
    pushes drawn with it (a stored protocol without the key was drawn before it: no limit)."""
    from biopsynav.network.data import rigid_chest_compression

    rigid = {"probe": {"rigid_share": 1.0, "max_chest_compression": 0.6}}
    assert rigid_chest_compression(rigid) == 0.6
    assert rigid_chest_compression({"probe": {"rigid_share": 1.0}}) == 0.0
    assert rigid_chest_compression({"probe": {"max_chest_compression": 0.6}}) == 0.0
    assert rigid_chest_compression({}) == 0.0
