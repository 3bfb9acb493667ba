"""examples/bound_shells.py: what `serve` sends for one push, decoded and drawn."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "bound_shells.py"


def load_example():
    spec = importlib.util.spec_from_file_location("bound_shells", EXAMPLE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_a_push_sends_every_lesion_in_a_shell_and_the_picture_is_drawn(trained_case, tmp_path):
    example = load_example()
    models = example.served_models(trained_case, 0, 8.0)
    lesions = [name for name in models if name.startswith("Lesion") and
               not name.endswith("Bound")]
    assert lesions and "BreastSkin" in models
    for name in lesions:
        (points, tris), (shell, shell_tris) = models[name], models[name + "Bound"]
        np.testing.assert_array_equal(shell_tris, tris)
        out = np.linalg.norm(shell - points, axis=1)
        assert np.all(out > 0.0) and np.ptp(out) < 1e-3  # one bound per lesion, pushed
        centre = points.mean(axis=0)
        assert np.all(np.linalg.norm(shell - centre, axis=1) >
                      np.linalg.norm(points - centre, axis=1))  # outwards
    png = tmp_path / "shells.png"
    assert example.main([str(trained_case), "--depth", "8", "--out", str(png)]) == 0
    assert png.stat().st_size > 10_000


def test_a_bad_case_lesion_or_depth_is_one_line_naming_it(trained_case, tmp_path, capsys):
    example = load_example()
    png = tmp_path / "shells.png"
    assert example.main([str(tmp_path / "nowhere"), "--out", str(png)]) == 2
    assert "bound_shells.py: error:" in capsys.readouterr().err
    for bad, says in ((["--lesion", "99"], "--lesion 99"), (["--depth", "nan"], "--depth nan")):
        with pytest.raises(SystemExit):
            example.main([str(trained_case), *bad, "--out", str(png)])
        assert says in capsys.readouterr().err
    assert not png.exists()
