"""Pretrained networks of other breasts a training starts from (``[network] prior``)."""

from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from biopsynav import prior_registry as priors
from biopsynav.config import NetworkSection
from biopsynav.errors import InputError
from biopsynav.network.priors import export_prior
from biopsynav.network.train import train
from biopsynav.network.unet import UNet3d, section_spec

from .synth import SHAPE, tiny_settings, write_synthetic_dataset

ARCH = section_spec(tiny_settings()).to_dict()


def _surface(seed: int) -> SimpleNamespace:
    rng = np.random.default_rng(seed)
    return SimpleNamespace(vertices=rng.normal(size=(10, 3)), faces=np.arange(9).reshape(3, 3))


@pytest.fixture()
def exported(trained, tmp_path, monkeypatch):
    """The synthetic case's trained model exported as the prior ``other`` (surface of seed 1),
    registered alone."""
    source_case, _ = trained
    path = export_prior(source_case / "model", "other", "a test network",
                               priors.surface_fingerprint(_surface(1)), "synthetic",
                               out_dir=tmp_path / "priors")
    prior = priors.Prior("other", path, json.loads(path.with_suffix(".json").read_text()))
    monkeypatch.setattr(priors, "PRIORS", {"other": prior})
    return prior


@pytest.fixture(scope="module")
def other_case(tmp_path_factory):
    case = tmp_path_factory.mktemp("prior") / "case"
    write_synthetic_dataset(case, shape=SHAPE, n_train=20, n_test=10, seed=11)
    return case


def test_training_starts_from_the_priors_weights_with_its_own_normalisation(
        exported, trained, other_case, tmp_path):
    s = tiny_settings(iterations=2, val_interval=1, learning_rate=1e-9, warmup_iterations=0,
                      prior="other")
    assert train(other_case, settings=s, model_dir=tmp_path / "m", progress=False).finished
    end = torch.load(tmp_path / "m" / "checkpoint.pt", weights_only=False)["model"]
    for key, value in exported.state_dict().items():  # a rate of 1e-9 leaves them as they began
        assert torch.allclose(value, end[f"unet.{key}"], atol=1e-6), key
    meta = json.loads((tmp_path / "m" / "meta.json").read_text())
    source = json.loads((trained[0] / "model" / "meta.json").read_text())
    assert meta["training"]["prior"]["name"] == "other"
    assert meta["training"]["prior"]["checksum"] == exported.checksum()
    assert meta["normalisation"]["in_scale"] != source["normalisation"]["in_scale"]  # its own


def test_float16_weights_stay_within_their_rounding_of_the_trained_ones(exported, trained):
    best = torch.load(trained[0] / "model" / "best.pt", weights_only=True)["model"]
    for key, value in exported.state_dict().items():
        assert torch.allclose(value, best[key].float(), rtol=1e-3, atol=1e-4), key


def test_auto_never_starts_from_the_cases_own_breast(exported):
    own = _surface(1)
    prior, line = priors.choose_prior("auto", lambda: own, ARCH)
    assert prior is None and "from scratch" in line
    prior, line = priors.choose_prior("auto", lambda: _surface(2), ARCH)
    assert prior is exported and "'other'" in line


def test_auto_skips_a_prior_of_another_architecture_without_reading_the_anatomy(exported):
    def no_anatomy():
        raise AssertionError("the anatomy is read only when a prior could apply")

    prior, line = priors.choose_prior("auto", no_anatomy, {**ARCH, "base_channels": 4})
    assert prior is None and "architecture" in line


def test_a_named_prior_of_another_architecture_is_refused(exported):
    with pytest.raises(InputError) as err:
        priors.choose_prior("other", lambda: _surface(2), {**ARCH, "levels": 2})
    assert err.value.where == "[network] prior" and "architecture" in str(err.value)


def test_none_trains_from_scratch(exported):
    assert priors.choose_prior("none", lambda: _surface(2), ARCH)[0] is None


def test_a_model_trained_from_a_prior_is_not_exported_as_one(exported, other_case, tmp_path):
    s = tiny_settings(iterations=2, val_interval=1, prior="other")
    train(other_case, settings=s, model_dir=tmp_path / "m", progress=False)
    with pytest.raises(InputError, match="trained from scratch"):
        export_prior(tmp_path / "m", "again", "", "0" * 64, "x", out_dir=tmp_path / "p")


def test_the_packaged_priors_load_into_the_default_network():
    spec = section_spec(NetworkSection())
    assert list(priors.PRIORS)[:2] == ["ucdavis-breast3", "phantom"]
    for prior in priors.PRIORS.values():
        assert prior.architecture == spec.to_dict()
        UNet3d(spec).load_state_dict(prior.state_dict())  # strict: every weight, no other


def test_auto_starts_the_phantom_from_the_uc_davis_breast_and_none_is_the_default(tmp_path):
    from biopsynav.case import make_phantom_case

    case = make_phantom_case(tmp_path / "ph")
    assert case.cfg.network.prior == "none"
    spec = section_spec(case.cfg.network).to_dict()
    prior, _ = priors.choose_prior("auto", lambda: case.anatomy, spec)
    assert prior.name == "ucdavis-breast3"


def test_a_damaged_or_mismatched_prior_is_named_not_a_numpy_error(exported, tmp_path):
    """A registered prior whose file is damaged, missing or of another network fails with an
    InputError that names the prior and its file."""
    spec = section_spec(tiny_settings())
    damaged = tmp_path / "damaged.npz"
    damaged.write_bytes(b"not a zip file")
    bad = priors.Prior("damaged", damaged, exported.info)
    for call in (bad.state_dict, lambda: bad.load_into(UNet3d(spec))):
        with pytest.raises(InputError, match="'damaged'.*damaged.npz"):
            call()
    plain = tmp_path / "plain.npz"
    with plain.open("wb") as f:
        np.save(f, np.zeros(3))  # an .npy under the .npz name
    with pytest.raises(InputError, match="'plain'.*plain.npz"):
        priors.Prior("plain", plain, exported.info).state_dict()
    missing = priors.Prior("gone", tmp_path / "gone.npz", exported.info)
    with pytest.raises(InputError, match="'gone'.*gone.npz"):
        missing.checksum()
    other = tmp_path / "other.npz"
    np.savez(other, **{k: np.zeros(1, np.float16) for k in exported.state_dict()})
    with pytest.raises(InputError, match="'shaped' .*does not fit this network"):
        priors.Prior("shaped", other, exported.info).load_into(UNet3d(spec))
