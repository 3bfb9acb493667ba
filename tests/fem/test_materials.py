"""Material laws: one registry, read by case.toml's validation and by the FE model."""

from __future__ import annotations

import numpy as np
import pytest

from biopsynav import materials
from biopsynav.config import config_from_dict
from biopsynav.errors import InputError


def test_a_registered_law_takes_its_own_tissue_parameters(monkeypatch, phantom_case):
    """A law with other parameters (shear and bulk moduli) is one registration: case.toml
    validates tissues against its parameters and the FE model gets the Lame constants it
    computes, on the neo-Hookean kernel branch."""
    from biopsynav.fem import FEModel

    def lame(p):
        return p["mu_mpa"], p["K_mpa"] - 2.0 * p["mu_mpa"] / 3.0

    def small_strain(p):
        mu, k = p["mu_mpa"], p["K_mpa"]
        return 9 * k * mu / (3 * k + mu), (3 * k - 2 * mu) / (2 * (3 * k + mu))

    law = materials.MaterialLaw("neo-hookean-mu-k", materials.KERNEL_NEO_HOOKEAN,
                                {"mu_mpa": (0.0, 1e3), "K_mpa": (0.0, 1e5)}, lame, small_strain)
    monkeypatch.setitem(materials.MATERIAL_LAWS, law.name, law)
    tissues = {"phantom": {"mu_mpa": 1.0e-3, "K_mpa": 30e-3}}
    with pytest.raises(InputError, match="of .refine. material_model; both laws read"):
        config_from_dict({"material": {"model": law.name, "tissues": tissues,
                                       "default_tissue": "phantom"}}, "t")
    cfg = config_from_dict({"material": {"model": law.name, "tissues": tissues,
                                         "default_tissue": "phantom"},
                            "refine": {"material_model": law.name}}, "t")
    monkeypatch.setattr(phantom_case, "cfg", cfg)  # a session fixture: restored after
    model = FEModel.from_case(phantom_case)
    assert model.material_id == materials.KERNEL_NEO_HOOKEAN
    np.testing.assert_allclose(model.mu, 1.0e-3)
    np.testing.assert_allclose(model.lam, 30e-3 - 2e-3 / 3)
    e, nu = small_strain({k: np.float64(v) for k, v in tissues["phantom"].items()})
    got = np.array(materials.lame_constants(model.E_mpa, model.nu))
    np.testing.assert_allclose(got, np.array(materials.lame_constants(e, nu))[:, None] + 0 * got)
    np.testing.assert_allclose(got[0], 1.0e-3)  # the small-strain (E, nu) give the same mu
    with pytest.raises(InputError, match="needs exactly mu_mpa and K_mpa"):
        config_from_dict({"material": {"model": law.name}}, "t")  # E_mpa/nu tissues refused
    with pytest.raises(InputError,
                       match="one of neo-hookean, neo-hookean-sri, neo-hookean-split-sri, "
                             "neo-hookean-split-sri-inner, svk, "
                             "neo-hookean-mu-k"):
        config_from_dict({"material": {"model": "ogden"}}, "t")
