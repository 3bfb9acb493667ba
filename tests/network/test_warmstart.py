"""Training that starts from another trained model (``[network] init_from``)."""

from __future__ import annotations

import json

import pytest
import torch

from biopsynav.errors import InputError
from biopsynav.network.train import train

from .synth import SHAPE, tiny_settings, write_synthetic_dataset


@pytest.fixture(scope="module")
def second_case(tmp_path_factory):
    """Other samples on the same grid as the shared synthetic data set: a second teacher."""
    case = tmp_path_factory.mktemp("second") / "case"
    write_synthetic_dataset(case, shape=SHAPE, n_train=20, n_test=10, seed=7)
    return case


def _unet_weights(model_dir) -> dict:
    return torch.load(model_dir / "best.pt", weights_only=True)["model"]


def test_training_starts_from_the_source_weights_and_normalisation(trained, second_case,
                                                                   tmp_path):
    source_case, _ = trained
    source = source_case / "model"
    s = tiny_settings(iterations=2, val_interval=1, learning_rate=1e-9, warmup_iterations=0,
                      init_from=str(source))
    summary = train(second_case, settings=s, model_dir=tmp_path / "m", progress=False)
    assert summary.finished
    start = _unet_weights(source)
    end = torch.load(tmp_path / "m" / "checkpoint.pt", weights_only=False)["model"]
    for key, value in start.items():  # a learning rate of 1e-9 leaves them where they began
        assert torch.allclose(value, end[f"unet.{key}"], atol=1e-6), key
    meta = json.loads((tmp_path / "m" / "meta.json").read_text())
    src_meta = json.loads((source / "meta.json").read_text())
    assert meta["normalisation"]["in_scale"] == src_meta["normalisation"]["in_scale"]
    assert meta["normalisation"]["out_scale"] == src_meta["normalisation"]["out_scale"]
    assert meta["training"]["init_from"]["checksum"] == src_meta["checksum"]
    for key, value in src_meta["envelope"].items():  # both data sets taught it
        assert meta["envelope"][key] >= value


def test_training_from_the_source_beats_training_from_scratch(trained, second_case, tmp_path):
    source_case, _ = trained
    s = tiny_settings(iterations=40, val_interval=20)
    scratch = train(second_case, settings=s, model_dir=tmp_path / "a", progress=False)
    warm = train(second_case, settings=tiny_settings(iterations=40, val_interval=20,
                                                     init_from=str(source_case / "model")),
                 model_dir=tmp_path / "b", progress=False)
    assert warm.best_val_e_mm < scratch.best_val_e_mm


def test_a_source_of_another_network_is_refused_naming_the_difference(trained, second_case,
                                                                      tmp_path):
    source_case, _ = trained
    s = tiny_settings(iterations=2, base_channels=4, init_from=str(source_case / "model"))
    with pytest.raises(InputError) as err:
        train(second_case, settings=s, model_dir=tmp_path / "m", progress=False)
    assert err.value.where == "[network] init_from"
    assert "architecture" in str(err.value)
    assert not (tmp_path / "m" / "checkpoint.pt").exists()


def test_a_missing_source_is_refused_naming_its_path(second_case, tmp_path):
    s = tiny_settings(iterations=2, init_from=str(tmp_path / "nowhere"))
    with pytest.raises(InputError) as err:
        train(second_case, settings=s, model_dir=tmp_path / "m", progress=False)
    assert "nowhere" in str(err.value) and err.value.where == "[network] init_from"


def test_a_source_with_unreadable_weights_is_refused_and_left_as_it_was(trained, second_case,
                                                                        tmp_path):
    import shutil

    source_case, _ = trained
    source = tmp_path / "source"
    shutil.copytree(source_case / "model", source)
    (source / "best.pt").write_bytes(b"not a torch file")
    s = tiny_settings(iterations=2, init_from=str(source))
    with pytest.raises(InputError) as err:
        train(second_case, settings=s, model_dir=tmp_path / "m", progress=False)
    assert "best.pt" in str(err.value) and err.value.where == "[network] init_from"
    assert (source / "best.pt").read_bytes() == b"not a torch file"
    assert not (tmp_path / "m" / "checkpoint.pt").exists()
