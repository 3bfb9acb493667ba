"""report.html as a browser shows it: headless Chromium screenshots the first screen.

Runs where Debian's ``chromium`` is installed (``make browser-check`` installs it and sets
``BIOPSYNAV_BROWSER=1``, which turns a missing browser into a failure).
"""

from __future__ import annotations

import os
import shutil
import subprocess

import numpy as np
import pytest

from biopsynav.report import write_report

from .test_report import _fake_outputs

pytestmark = pytest.mark.browser

FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--hide-scrollbars"]
TABLE_HEADER_RGB = (238, 238, 255)  # th{background:#eef}


def _chromium() -> str:
    path = shutil.which("chromium")
    if path is None:
        if os.environ.get("BIOPSYNAV_BROWSER"):
            pytest.fail("chromium is missing (make browser-check installs it)")
        pytest.skip("chromium is not installed (make browser-check)")
    return path


def test_first_screen_shows_the_tables_not_the_parameters(tmp_path):
    from matplotlib.image import imread

    from biopsynav.case import make_phantom_case

    case_dir = make_phantom_case(tmp_path / "case", cell_size_mm=15).dir
    _fake_outputs(case_dir)
    html = write_report(case_dir)[0]
    shot = tmp_path / "first_screen.png"
    subprocess.run([_chromium(), *FLAGS, f"--user-data-dir={tmp_path / 'profile'}",
                    f"--screenshot={shot}", "--window-size=1200,900", html.as_uri()],
                   capture_output=True, timeout=120, check=True)
    rgb = (imread(shot)[..., :3] * 255).round().astype(int)
    assert rgb.shape[:2] == (900, 1200)
    assert rgb.std() > 20, "a blank page"
    header = np.all(rgb == TABLE_HEADER_RGB, axis=2)
    assert header[:450].sum() > 2000, "no table header in the top half of the first screen"
    if os.environ.get("BIOPSYNAV_KEEP_SCREENSHOT"):
        shutil.copy(shot, os.environ["BIOPSYNAV_KEEP_SCREENSHOT"])
