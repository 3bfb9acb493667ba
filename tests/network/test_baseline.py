"""The linear-elastic physics baseline and the surrogate trained on its residual."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
import scipy.sparse as sp

from biopsynav.contact.baseline import LinearElasticBaseline
from biopsynav.errors import FingerprintError
from biopsynav.fem import FEModel, Loads, SolverSettings, solve
from biopsynav.grid.index import hex_connectivity

from .conftest import tiny_settings
from .synth import write_linear_elastic_dataset

SHAPE = (6, 5, 4)
SPACING = 5.0


def box_model() -> FEModel:
    """A 25 x 20 x 15 mm block of 5 mm hexahedra, bottom face (k = 0) fixed."""
    ijk_n = np.stack(np.meshgrid(*[np.arange(n) for n in SHAPE], indexing="ij"), -1)
    nodes = ijk_n.reshape(-1, 3) * SPACING
    cells = np.stack(np.meshgrid(*[np.arange(n - 1) for n in SHAPE], indexing="ij"), -1)
    hexes = hex_connectivity(cells.reshape(-1, 3), SHAPE)
    fixed = ijk_n.reshape(-1, 3)[:, 2] == 0
    return FEModel(nodes, hexes, 1.0, 0.003, 0.45, fixed)


def top_nodes() -> np.ndarray:
    ijk = np.stack(np.meshgrid(*[np.arange(n) for n in SHAPE], indexing="ij"), -1)
    return np.flatnonzero(ijk.reshape(-1, 3)[:, 2] == SHAPE[2] - 1)


def contact_input(nodes: np.ndarray, g: np.ndarray, weight: float = 1.0) -> np.ndarray:
    x = np.zeros((4, int(np.prod(SHAPE))), np.float32)
    x[:3, nodes] = g.T
    x[3, nodes] = weight
    return x.reshape(4, *SHAPE)


@pytest.fixture(scope="module")
def box():
    model = box_model()
    return model, LinearElasticBaseline.from_model(model, top_nodes(), SHAPE, np.float64,
                                                   spring=None)


def test_hard_baseline_is_the_fe_solution_of_a_small_prescribed_displacement(box):
    """Hard constraints on nodes = the FE solve with those node displacements prescribed
    (0.01 mm: the neo-Hookean model is linear to ~1e-4 there), every other node force-free."""
    model, base = box
    top = top_nodes()
    rng = np.random.default_rng(0)
    contact = rng.choice(top, 6, replace=False)
    g = rng.normal(size=(6, 3)) * 0.01
    pred = base.predict(contact_input(contact, g))
    select = sp.csr_matrix((np.ones(6), (np.arange(6), contact)), shape=(6, model.n_nodes))
    u, _ = solve(model, Loads(prescribed_matrix=select, prescribed_displacement=g),
                 SolverSettings(backend="superlu"))
    u_fe = u.T.reshape(3, *SHAPE)
    assert np.abs(pred.reshape(3, -1)[:, contact].T - g).max() < 1e-6  # exact at the contact
    assert np.abs(pred - u_fe).max() < 2e-3 * np.abs(u_fe).max()
    assert np.abs(pred.reshape(3, -1)[:, ~model.fixed[:, 0]]).max() > 0  # it moves the rest
    assert np.all(pred.reshape(3, -1)[:, model.fixed[:, 0]] == 0)  # chest wall fixed


def test_springs_tend_to_hard_constraints_and_weaken_with_small_weights(box):
    model, base = box
    contact = top_nodes()[:4]
    g = np.tile([0.0, 0.0, -1.0], (4, 1))
    x = contact_input(contact, g)
    hard = base.predict(x)
    stiff = LinearElasticBaseline.from_model(model, top_nodes(), SHAPE, np.float64, spring=1e7)
    assert np.abs(stiff.predict(x) - hard).max() < 1e-4
    soft = LinearElasticBaseline.from_model(model, top_nodes(), SHAPE, np.float64, spring=0.3)
    heavy, light = soft.predict(x), soft.predict(contact_input(contact, g, weight=0.1))
    assert np.abs(light).max() < np.abs(heavy).max() <= np.abs(hard).max() + 1e-9


@pytest.mark.parametrize("spring", [None, 0.3])
def test_contact_operator_equals_predict_for_a_fixed_contact_set(spring):
    model = box_model()
    base = LinearElasticBaseline.from_model(model, top_nodes(), SHAPE, np.float64, spring=spring)
    rng = np.random.default_rng(1)
    contact = rng.choice(top_nodes(), 7, replace=False)
    weights = np.zeros(int(np.prod(SHAPE)))
    weights[contact] = rng.uniform(0.2, 2.0, 7)
    rows = sp.random(5, 3 * weights.size, density=0.05, random_state=2, format="csr")
    positions, full = base.contact_operator(weights)
    _, restricted = base.contact_operator(weights.reshape(SHAPE), rows)
    for _ in range(3):
        x = contact_input(contact, rng.normal(size=(7, 3)))
        x[3] = weights.reshape(SHAPE)
        expected = base.predict(x).ravel()
        flat = x[:3].ravel()[positions]
        tol = 1e-5 * np.abs(expected).max()  # predict returns float32
        assert np.allclose(full @ flat, expected, rtol=0, atol=tol)
        assert np.allclose(restricted @ flat, rows @ expected, rtol=0, atol=tol * 10)


def test_zero_input_gives_zero_and_batches_match(box):
    _, base = box
    assert np.all(base.predict(np.zeros((4, *SHAPE), np.float32)) == 0)
    contact = top_nodes()[3:7]
    x = np.stack([contact_input(contact, np.full((4, 3), 0.5)), np.zeros((4, *SHAPE))])
    batch = base.predict(x)
    assert batch.shape == (2, 3, *SHAPE)
    assert np.array_equal(batch[0], base.predict(x[0])) and np.all(batch[1] == 0)


# --- a real (coarse) phantom case: training on the residual and the Surrogate round trip ---

@pytest.fixture(scope="module")
def phantom(tmp_path_factory):
    """The phantom at 24 mm cells (16 x 8 x 8 nodes) with a small data set whose targets are
    the hard linear-elastic response plus a smooth non-linear term."""
    from biopsynav.case import make_phantom_case

    case_dir = tmp_path_factory.mktemp("phantom") / "case"
    case = make_phantom_case(case_dir, cell_size_mm=24.0,
                             overrides={"refine": {"samples": 0}})  # its model is the tracker's
    x = write_linear_elastic_dataset(case, n_train=12, n_test=4, seed=3)
    return case_dir, case, x


@pytest.fixture(scope="module")
def trained_le(phantom):
    from biopsynav.network.train import train

    case_dir, _, _ = phantom
    settings = tiny_settings(levels=2, iterations=20, val_interval=10, warmup_iterations=5,
                             baseline="linear-elastic")
    summary = train(case_dir, settings=settings, progress=False)
    return case_dir / "model", summary


def test_surrogate_adds_the_baseline_to_the_residual_net(phantom, trained_le):
    import torch

    from biopsynav.inference.runtimes import load_torchscript
    from biopsynav.inference.surrogate import Surrogate

    case_dir, case, x = phantom
    model_dir, summary = trained_le
    meta = json.loads((model_dir / "meta.json").read_text())
    assert meta["baseline"]["kind"] == "linear-elastic" and summary.finished
    sur = Surrogate.load(model_dir, case.fingerprint(), runtime="torchscript", threads=1,
                         warmup=2)
    assert sur.baseline is not None
    base = LinearElasticBaseline.from_case(case, spring=meta["baseline"]["spring"])
    net = load_torchscript(model_dir / "model.ts")
    with torch.inference_mode():
        residual = net(torch.from_numpy(x[:3])).numpy()
    expect = residual + base.predict(x[:3])
    assert np.abs(sur.predict(x[:3]) - expect).max() < 1e-4
    assert np.abs(sur.predict(x[0]) - expect[0]).max() < 1e-4
    # same case passed explicitly
    sur2 = Surrogate.load(model_dir, case.fingerprint(), runtime="torchscript", threads=1,
                          warmup=0, case=case)
    assert np.abs(sur2.predict(x[0]) - expect[0]).max() < 1e-4
    from biopsynav.inference.surrogate import openvino_available

    if openvino_available():  # the network started asynchronously beside the baseline
        ov = Surrogate.load(model_dir, case.fingerprint(), runtime="openvino", threads=1,
                            warmup=2, case=case)
        assert np.abs(ov.predict(x[:3]) - expect).max() < 1e-3
        first = ov.predict(x[0])
        ov.predict(x[1])  # the request's buffer is reused: earlier results must not change
        assert np.abs(first - expect[0]).max() < 1e-3


def test_fingerprint_refusal_with_baseline(phantom, trained_le, tmp_path):
    import shutil

    from biopsynav.inference.model_files import meta_checksum
    from biopsynav.inference.surrogate import Surrogate

    _, case, _ = phantom
    model_dir, _ = trained_le
    with pytest.raises(FingerprintError):
        Surrogate.load(model_dir, "another-patient", runtime="torchscript", threads=1)
    # a model folder claiming another fingerprint must not get this case's baseline either
    other = tmp_path / "model"
    shutil.copytree(model_dir, other)
    meta = json.loads((other / "meta.json").read_text())
    meta["fingerprint"] = "another-patient"
    meta["checksum"] = meta_checksum(meta)  # a whole model of another patient, not a damaged one
    (other / "meta.json").write_text(json.dumps(meta))
    with pytest.raises(FingerprintError):
        Surrogate.load(other, "another-patient", runtime="torchscript", threads=1, case=case)


def test_baseline_none_keeps_the_old_behaviour(phantom, tmp_path):
    from biopsynav.inference.surrogate import Surrogate
    from biopsynav.network.train import train

    case_dir, case, x = phantom
    settings = tiny_settings(levels=2, iterations=4, val_interval=4, warmup_iterations=1,
                             baseline="none")
    train(case_dir, settings=settings, model_dir=tmp_path / "m", progress=False)
    meta = json.loads((tmp_path / "m" / "meta.json").read_text())
    assert meta["baseline"]["kind"] == "none"
    sur = Surrogate.load(tmp_path / "m", case.fingerprint(), runtime="torchscript",
                         threads=1, warmup=0)
    assert sur.baseline is None and sur.predict(x[0]).shape == (3, *case.grid.node_shape)


@pytest.mark.parametrize("projection", [True, False])
def test_tracker_hot_path_with_the_lesion_operator_equals_the_full_prediction(
        phantom, trained_le, projection, monkeypatch):
    """Tracker.update (network residual at the lesions + precomputed baseline operators)
    gives the lesion positions of the full-grid path (``with_surface``: Surrogate.predict),
    with the contact projection and without."""
    from biopsynav.inference.surrogate import Surrogate
    from biopsynav.tracker import Tracker

    _, case, _ = phantom
    model_dir, _ = trained_le
    monkeypatch.setattr(case.cfg.network, "contact_projection", projection)
    sur = Surrogate.load(model_dir, case.fingerprint(), runtime="torchscript", threads=1,
                         warmup=0, case=case)
    assert sur.can_project
    tracker = Tracker(case, "net", surrogate=sur)
    top = np.array([[1.0, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, 75.0], [0, 0, 0, 1]])
    assert tracker.set_rest_pose(top) > 0 and tracker._net.lesion_op is not None
    assert tracker.projects_contact == projection
    for depth, angle in ((3.0, 0.0), (8.0, 0.1)):
        pose = top.copy()
        pose[2, 3] -= depth
        c, s = np.cos(angle), np.sin(angle)
        pose[:3, :3] = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) @ pose[:3, :3]
        fast, full = tracker.update(pose), tracker.update(pose, with_surface=True)
        assert fast.status == full.status == "ok"
        moved = np.array([les.displacement for les in full.lesions])
        assert np.abs(moved).max() > 0.1
        assert np.abs(np.array([les.displacement for les in fast.lesions]) - moved).max() < 1e-4
        grid = tracker.update(pose, with_field=True).grid_displacement  # the whole field too
        assert full.grid_displacement is None and grid.shape == (case.grid.n_nodes, 3)
        assert np.abs(tracker._centre_emb.interpolate(grid) - moved).max() < 1e-6
        fast_s = tracker.update(pose, lesion_surfaces=True)  # the lesion meshes too
        full_s = tracker.update(pose, with_surface=True, lesion_surfaces=True)
        for a, b, c in zip(fast_s.lesions, full_s.lesions, fast.lesions, strict=True):
            assert a.surface is not None and np.abs(a.surface - b.surface).max() < 1e-4
            assert c.surface is None and np.abs(a.center - c.center).max() < 1e-9


def test_tracker_refuses_pushes_deeper_than_the_deepest_trained_one(phantom, trained_le):
    """A probe displacement beyond ``envelope_margin`` x the envelope's ``max_probe_disp_mm``
    gives out_of_envelope and no numbers; within it, lesion positions; a model without the
    figure (trained before it was recorded) has only the contact bound."""
    from biopsynav.inference.surrogate import Surrogate
    from biopsynav.tracker import Tracker

    _, case, _ = phantom
    model_dir, _ = trained_le
    sur = Surrogate.load(model_dir, case.fingerprint(), runtime="torchscript", threads=1,
                         warmup=0, case=case)
    tracker = Tracker(case, "net", surrogate=sur)
    assert tracker.max_probe_mm == np.inf  # the synthetic store has no probe displacements
    top = np.array([[1.0, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, 75.0], [0, 0, 0, 1]])
    tracker.set_rest_pose(top)
    tracker.max_contact_mm = np.inf
    pose = top.copy()
    pose[2, 3] -= 8.0
    depth = float(np.linalg.norm(tracker.contact_displacement(pose), axis=1).mean())
    assert 6.0 < depth < 10.0
    tracker.max_probe_mm = 1.01 * depth / tracker.envelope_margin
    assert tracker.update(pose).status == "ok"
    tracker.max_probe_mm = 0.99 * depth / tracker.envelope_margin
    deep = tracker.update(pose)
    assert deep.status == "out_of_envelope" and "deepest trained push" in deep.reason
    assert all(not np.all(np.isfinite(les.center)) for les in deep.lesions or [])


def test_tracker_refuses_pushes_compressing_the_tissue_beyond_the_trained_share(phantom,
                                                                                trained_le):
    """A push that moves the face towards the chest wall by more than ``envelope_margin`` x
    the envelope's ``max_chest_compression`` of the tissue under the face gives
    out_of_envelope, naming the share; a model without the figure has no such limit."""
    from biopsynav.inference.surrogate import Surrogate
    from biopsynav.probe import chest_distance
    from biopsynav.tracker import Tracker

    _, case, _ = phantom
    model_dir, _ = trained_le
    sur = Surrogate.load(model_dir, case.fingerprint(), runtime="torchscript", threads=1,
                         warmup=0, case=case)
    tracker = Tracker(case, "net", surrogate=sur)
    assert tracker.max_compression == 0.0  # no rigid pushes in the synthetic store
    top = np.array([[1.0, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, 75.0], [0, 0, 0, 1]])
    n_contact = tracker.set_rest_pose(top)
    tissue = chest_distance(case.anatomy, tracker._contact)
    assert n_contact and 40.0 < tissue < 80.0  # the dome's top, its chest wall below
    tracker.max_contact_mm = np.inf
    pose = top.copy()
    pose[2, 3] -= 8.0  # straight down, towards the chest wall
    compression = -tracker.contact_displacement(pose).mean(axis=0)[2] / tissue
    assert tracker.update(pose).status == "ok"
    tracker.max_compression = 1.01 * compression / tracker.envelope_margin
    assert tracker.update(pose).status == "ok"
    tracker.max_compression = 0.99 * compression / tracker.envelope_margin
    deep = tracker.update(pose)
    assert deep.status == "out_of_envelope" and "in front of the chest wall" in deep.reason
    assert f"{100 * compression:.0f} %" in deep.reason


def test_training_with_the_baseline_resumes_from_its_checkpoint(phantom, tmp_path):
    """The baseline's set-up timings must not enter the checkpoint signature (they did: every
    run with a baseline trained afresh)."""
    from biopsynav.network.train import train

    case_dir, _, _ = phantom
    settings = tiny_settings(levels=2, iterations=8, val_interval=4, warmup_iterations=1,
                             baseline="linear-elastic")
    first = train(case_dir, settings=settings, model_dir=tmp_path / "m", progress=False,
                  stop_after=4)
    assert not first.finished and first.iterations_done == 4
    second = train(case_dir, settings=settings, model_dir=tmp_path / "m", progress=False)
    assert second.resumed_from == 4 and second.finished


def test_tracker_load_takes_the_network_thread_count(phantom, trained_le):
    """``Tracker.load(threads=...)`` (the service's ``[igtl] inference_threads``) reaches the
    runtime."""
    pytest.importorskip("openvino")
    from biopsynav.tracker import Tracker

    case_dir, _, _ = phantom
    for threads in (1, 2):
        run = Tracker.load(case_dir, threads=threads)._surrogate._run
        assert run.name.startswith("openvino") and run.threads == threads
    from biopsynav.igtl.service import service_tracker

    served = service_tracker(case_dir)._surrogate._run  # [igtl] inference_threads = 2
    assert served.name.startswith("openvino") and served.threads == min(2, os.cpu_count())


def test_tracker_load_takes_the_case_runtime(phantom, trained_le):
    """``Tracker.load`` runs the tracking model on the case's ``[network] runtime``, as
    ``load_for_case`` does, whatever runtime the model was exported for."""
    import copy

    from biopsynav.case import Case
    from biopsynav.tracker import Tracker

    _, case, _ = phantom
    cfg = copy.deepcopy(case.cfg)
    cfg.network.runtime = "torchscript"
    chosen = Case(case.dir, cfg, case.anatomy, case.grid)
    assert Tracker.load(chosen, engine="net")._surrogate._run.name == "torchscript"


def test_surrogate_predict_with_the_contact_projection(phantom, trained_le):
    """``Surrogate.predict(x, projection, g)`` is the projected residual net (TorchScript and
    OpenVINO's asynchronous path alike) and moves three contact points by ``g``."""
    from biopsynav.errors import InputError
    from biopsynav.grid.embedding import Embedding
    from biopsynav.grid.index import field_to_tensor
    from biopsynav.inference.surrogate import Surrogate, openvino_available

    _, case, x = phantom
    model_dir, _ = trained_le
    sur = Surrogate.load(model_dir, case.fingerprint(), runtime="torchscript", threads=1,
                         warmup=0, case=case)
    a = case.anatomy
    top = np.argsort(a.vertices[:, 2])[-400:][[0, 150, 399]]
    contact = Embedding.build(case.grid, a.vertices[top], where="contact").matrix
    proj = sur.contact_projection(contact)
    g = np.array([[0.0, 0, -3], [0.5, 0, -4], [0, 0.2, -3.5]])
    xin = field_to_tensor(proj.input_op.field(g), case.grid.node_shape).astype(np.float32)
    expect = proj.project(xin, g, sur.predict_network(xin))
    out = sur.predict(xin, proj, g)
    assert np.abs(out - expect).max() < 1e-5
    assert np.abs(proj.point_displacement(out) - g).max() < 5e-3
    with pytest.raises(InputError, match="both the contact projection"):
        sur.predict(xin, proj)
    with pytest.raises(InputError, match="one input at a time"):
        sur.predict(x[:2], proj, g)
    if openvino_available():
        ov = Surrogate.load(model_dir, case.fingerprint(), runtime="openvino", threads=1,
                            warmup=1, case=case)
        with pytest.raises(InputError, match="another model"):
            ov.predict(xin, proj, g)
        assert np.abs(ov.predict(xin, ov.contact_projection(contact), g) - expect).max() < 1e-3
