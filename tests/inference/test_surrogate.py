"""Inference: exported model equals eager, fingerprints enforced, bad files reported clearly."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import torch

from biopsynav.errors import FingerprintError, InputError
from biopsynav.inference.surrogate import Surrogate, openvino_available
from biopsynav.network.data import load_dataset
from biopsynav.network.evaluate import evaluate
from biopsynav.network.export import SurrogateNet
from biopsynav.network.unet import UNetSpec

from ..network.synth import FINGERPRINT


def _eager(model_dir) -> SurrogateNet:
    meta = json.loads((model_dir / "meta.json").read_text())
    data_active = np.zeros(meta["node_shape"], bool)
    norm = meta["normalisation"]
    quad = np.array(norm["quad_scale"]) if "quad_scale" in norm else None
    net = SurrogateNet(UNetSpec.from_dict(meta["architecture"]), np.array(norm["in_scale"]),
                       np.array(norm["out_scale"]), data_active, quad)
    best = torch.load(model_dir / "best.pt", weights_only=False)["model"]
    net.unet.load_state_dict(best)
    return net.eval()


@pytest.mark.parametrize("runtime", ["torchscript", "openvino"])
def test_exported_matches_eager(trained, runtime):
    if runtime == "openvino" and not openvino_available():
        pytest.skip("openvino not installed")
    case, _ = trained
    data = load_dataset(case)
    net = _eager(case / "model")
    net.mask.copy_(data.active.float()[None, None])
    sur = Surrogate.load(case / "model", FINGERPRINT, runtime=runtime, warmup=2)
    assert sur.runtime == runtime and sur.precision == "fp32"
    x = data.inputs[data.test_idx[:3]]
    with torch.no_grad():
        ref = net(x).numpy()
    batch = sur.predict(x.numpy())
    one = sur.predict(x[0].numpy())
    assert batch.shape == (3, 3, *data.node_shape) and one.shape == (3, *data.node_shape)
    np.testing.assert_allclose(batch, ref, atol=1e-5)
    np.testing.assert_allclose(one, ref[0], atol=1e-5)
    assert np.all(one[:, ~data.active.numpy()] == 0)


def test_the_bf16_runtime_predicts_like_fp32(trained):
    """On a CPU with bf16 arithmetic, OpenVINO in bfloat16 predicts within 1 % of the largest
    output of OpenVINO in fp32 (bf16 keeps 8 bits of mantissa), says so in ``precision``,
    and keeps inactive nodes at exactly zero."""
    from biopsynav.inference.runtimes import openvino_bf16_available

    if not openvino_bf16_available():
        pytest.skip("no AMX-BF16 or AVX-512 BF16 on this CPU, or openvino not installed")
    case, _ = trained
    data = load_dataset(case)
    fp32 = Surrogate.load(case / "model", FINGERPRINT, runtime="openvino", warmup=1)
    bf16 = Surrogate.load(case / "model", FINGERPRINT, runtime="openvino-bf16", warmup=1)
    assert (fp32.precision, bf16.precision) == ("fp32", "bf16")
    x = data.inputs[data.test_idx[:3]].numpy()
    ref, low = fp32.predict(x), bf16.predict(x)
    assert np.abs(low - ref).max() <= 0.01 * np.abs(ref).max()
    assert np.all(low[:, :, ~data.active.numpy()] == 0)


@pytest.mark.parametrize("unit", [None, "AVX-512 BF16", "AMX-BF16 tiles"])
def test_auto_takes_bf16_only_where_the_cpu_has_bf16_arithmetic(monkeypatch, unit):
    import biopsynav.inference.runtimes as R

    if not R.openvino_available():
        pytest.skip("openvino not installed")
    monkeypatch.setattr(R, "cpu_bf16_unit", lambda: unit)
    assert R.resolve_runtime("auto").name == ("openvino-bf16" if unit else "openvino")


@pytest.mark.parametrize("bf16_ms, chosen", [(1.0, "openvino-bf16"), (2.8, "openvino"),
                                             (1.95, "openvino")])
def test_auto_keeps_bf16_only_where_its_predictions_are_faster(trained, monkeypatch, bf16_ms,
                                                               chosen):
    """Where OpenVINO may run in bf16, ``auto`` times both arithmetics on the model and keeps
    bf16 only when clearly faster (a near tie keeps fp32); a runtime asked for by name is not
    timed; the loaded model and Table 1 say which and why."""
    import biopsynav.inference.runtimes as R

    if not R.openvino_bf16_available():
        pytest.skip("no AMX-BF16 or AVX-512 BF16 on this CPU, or openvino not installed")
    case, _ = trained
    timed = {"bf16": bf16_ms, "fp32": 2.0}
    calls = []
    monkeypatch.setattr(R, "AUTO_CHOICES", {})
    monkeypatch.setattr(R, "timed_predictions_ms", lambda runners, shape: calls.append(1) or [
        timed[r.precision] for r in runners])
    sur = Surrogate.load(case / "model", FINGERPRINT, runtime="auto", threads=2, warmup=1)
    assert sur.runtime == chosen
    assert f"{bf16_ms:.2f} ms in bf16 against 2.00 in fp32" in sur.runtime_chosen
    timed["bf16"] = 3.0 - bf16_ms  # a second load keeps the first's choice, untimed
    again = Surrogate.load(case / "model", FINGERPRINT, runtime="auto", threads=2, warmup=1)
    assert (again.runtime, again.runtime_chosen, len(calls)) == (chosen, sur.runtime_chosen, 1)
    one_thread = Surrogate.load(case / "model", FINGERPRINT, runtime="auto", threads=1,
                                warmup=1)  # another thread count is timed again
    assert len(calls) == 2 and one_thread.runtime_chosen != sur.runtime_chosen
    named = Surrogate.load(case / "model", FINGERPRINT, runtime="openvino-bf16", warmup=1)
    assert named.runtime == "openvino-bf16" and named.runtime_chosen == ""


def test_bf16_asked_for_on_a_cpu_without_bf16_says_what_it_needs(monkeypatch):
    import biopsynav.inference.runtimes as R

    monkeypatch.setattr(R, "cpu_bf16_unit", lambda: None)
    with pytest.raises(InputError, match="not available here: it needs the openvino package "
                                         "and a CPU with AMX-BF16 or AVX-512 BF16"):
        R.resolve_runtime("openvino-bf16")


def test_predict_rejects_bad_shape(trained):
    case, _ = trained
    sur = Surrogate.load(case / "model", FINGERPRINT, runtime="torchscript", warmup=0)
    with pytest.raises(InputError, match="input shape"):
        sur.predict(np.zeros((3, 16, 8, 8), np.float32))


def test_fingerprint_mismatch_refused(trained):
    case, _ = trained
    with pytest.raises(FingerprintError, match="another anatomy or grid"):
        Surrogate.load(case / "model", "some-other-patient")


def test_missing_and_corrupt_files(trained, tmp_path):
    case, _ = trained
    model = tmp_path / "model"
    shutil.copytree(case / "model", model)
    (model / "model.ts").write_bytes(b"garbage")
    with pytest.raises(InputError, match="corrupt"):
        Surrogate.load(model, FINGERPRINT, runtime="torchscript")
    (model / "model.ts").unlink()
    with pytest.raises(InputError, match="missing"):
        Surrogate.load(model, FINGERPRINT, runtime="torchscript")
    (model / "meta.json").write_text("{not json")
    with pytest.raises(InputError, match="corrupt"):
        Surrogate.load(model, FINGERPRINT)
    (model / "meta.json").unlink()
    with pytest.raises(InputError, match="no trained model"):
        Surrogate.load(model, FINGERPRINT)


def test_evaluate_writes_table1(trained, tmp_path):
    case, summary = trained
    r = evaluate(case / "model", case, tmp_path, FINGERPRINT, runtime="torchscript",
                 n_timing=30)
    for key in ("mean_e_mm", "std_e_mm", "max_e_mm", "predict_p50_ms", "predict_p99_ms",
                "train_min", "max_disp_mm"):
        assert np.isfinite(r[key]), key
    assert r["n_samples"] == 10 and r["max_e_mm"] >= r["mean_e_mm"]
    assert abs(r["mean_e_mm"] - summary.best_val_e_mm) < 1e-4  # deployed == validated
    assert r["contact_projection"] is False  # no baseline: nothing to project with
    assert r["mean_e_unprojected_mm"] == r["mean_e_mm"]
    for name in ("table1.json", "error_histogram.png", "worst_sample.png",
                 "largest_deformation.png"):
        assert (tmp_path / name).is_file(), name
    with pytest.raises(FingerprintError):
        evaluate(case / "model", case, tmp_path, "other")


def test_a_registered_runtime_is_a_case_toml_choice_and_runs(monkeypatch):
    """One registration (inference/runtimes.py) makes a runtime loadable by name and accepted by
    ``[network] runtime``; unknown names are refused with the known ones."""
    from biopsynav.config import config_from_dict
    from biopsynav.inference import runtimes

    class Zeros:
        name = "zeros"

        def __init__(self, path, threads, shape):
            self.shape = shape

        def __call__(self, x):
            return np.zeros((x.shape[0], 3, *self.shape), np.float32)

    monkeypatch.setitem(runtimes.RUNTIMES, "zeros",
                        runtimes.RuntimeSpec("zeros", runtimes.TORCHSCRIPT, Zeros))
    assert config_from_dict({"network": {"runtime": "zeros"}}, "t").network.runtime == "zeros"
    assert runtimes.resolve_runtime("zeros").make(None, 1, (2, 2, 2))(
        np.zeros((1, 4, 2, 2, 2), np.float32)).shape == (1, 3, 2, 2, 2)
    known = "one of auto, torchscript, openvino, openvino-bf16, zeros"
    with pytest.raises(InputError, match=known):
        config_from_dict({"network": {"runtime": "tensorrt"}}, "t")


def test_a_model_that_learnt_elastic_contact_is_never_projected(tmp_path):
    """The contact projection would move the points onto the face, which a teacher with
    elastic contact does not do (docs/network.md): such a model is not projected, whatever
    the case's switch says; any other hard-baseline model follows the switch."""
    from types import SimpleNamespace

    meta = {"node_shape": [2, 2, 2], "contact_input": "elastic", "baseline": {}}
    sur = Surrogate(SimpleNamespace(name="stub"), meta, tmp_path, SimpleNamespace(spring=None))
    assert sur.projects(True) and not sur.projects(False)
    meta["baseline"]["elastic_contact"] = True
    assert not sur.projects(True) and not sur.projects(False)


def test_table1_gives_the_physics_baseline_alone_beside_the_network(trained_case):
    """Table 1 of a model with a physics baseline also scores the baseline alone (the network
    with its head at zero) on the same held-out samples, recomputed here from the stored
    inputs and targets."""
    from biopsynav.inference.surrogate import case_fingerprint
    from biopsynav.network.metrics import mean_norm_error_np

    t1 = json.loads((trained_case / "eval" / "table1.json").read_text())
    data = load_dataset(trained_case)
    sur = Surrogate.load(trained_case / "model", case_fingerprint(trained_case))
    x = data.inputs[data.test_idx].numpy()
    e = mean_norm_error_np(sur.baseline.predict(x), data.targets[data.test_idx].numpy(),
                           data.active.numpy())
    assert t1["baseline_mean_e_mm"] == pytest.approx(float(e.mean()), rel=1e-6)
    assert t1["baseline_max_e_mm"] == pytest.approx(float(e.max()), rel=1e-6)
    assert t1["baseline_mean_e_mm"] != pytest.approx(t1["mean_e_mm"], rel=1e-3)  # it trained
