"""benchmarks/time_to_model.py: the options it sets in the new case are checked first, and
name the result file."""

from __future__ import annotations

import pytest

from tests.runs import BENCHMARKS


@pytest.mark.parametrize("option, value, named", [("--prior", "someone-else", "prior"),
                                                  ("--iterations", "0", "iterations")])
def test_a_bad_network_option_is_refused_before_any_work(option, value, named, tmp_path,
                                                         monkeypatch):
    monkeypatch.syspath_prepend(str(BENCHMARKS))
    import time_to_model

    with pytest.raises(SystemExit) as stop:
        time_to_model.main(["--case", "phantom", "--workdir", str(tmp_path), option, value])
    assert named in str(stop.value.code) and str(stop.value.code).startswith("time_to_model:")
    assert not (tmp_path / "phantom").exists()


def test_a_variant_of_the_defaults_never_takes_the_defaults_result_name(monkeypatch):
    monkeypatch.syspath_prepend(str(BENCHMARKS))
    import time_to_model

    assert time_to_model.result_name("phantom", None, None) == "time-to-model-phantom"
    assert time_to_model.result_name("phantom", "none", None) == "time-to-model-phantom"
    assert (time_to_model.result_name("ucdavis", "auto", 4000)
            == "time-to-model-ucdavis-prior-it4000")
    assert time_to_model.result_name("phantom", None, 5000) == "time-to-model-phantom-it5000"
