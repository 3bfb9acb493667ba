"""benchmarks/generate.py: its options are checked before a case is built."""

from __future__ import annotations

import subprocess
import sys

from tests.runs import BENCHMARKS


def test_an_unknown_recipe_is_refused_before_any_work(tmp_path):
    proc = subprocess.run([sys.executable, str(BENCHMARKS / "generate.py"), "--recipe", "nope"],
                          capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert "argument --recipe: invalid choice: 'nope'" in proc.stderr
    assert "phantom:" not in proc.stdout  # no case was built
