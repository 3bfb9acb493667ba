"""The test suite's wall time, as ``make test`` runs it (two pytest-xdist workers).

    python benchmarks/suite_time.py

Run it alone. Prints the 20 slowest tests (pytest's ``--durations``, where the suite's time
goes). Writes ``benchmarks/results/suite-time.json`` (minutes, passed, failed, skipped); the
last line reads ``RESULT minutes=... passed=... failed=... skipped=...``.
"""

from __future__ import annotations

import re
import subprocess
import sys
import time
from pathlib import Path

from resultfile import write_result

ROOT = Path(__file__).resolve().parents[1]
#: the pytest command of the Makefile's `test` target
COMMAND = ["-m", "pytest", "-q", "-n", "2", "--dist", "loadfile", "--no-loadscope-reorder",
           "--max-worker-restart", "0"]


#: the slowest tests printed
SLOWEST = 20


def counts(output: str) -> dict:
    """passed / failed / skipped / errors of pytest's last summary line."""
    last = output.strip().splitlines()[-1] if output.strip() else ""
    found = {k: int(n) for n, k in re.findall(r"(\d+) (passed|failed|skipped|errors?)", last)}
    return {k: found.get(k, 0) for k in ("passed", "failed", "skipped", "error")} | {
        "error": found.get("error", 0) + found.get("errors", 0)}


def main() -> int:
    start = time.perf_counter()
    run = subprocess.run([sys.executable, *COMMAND, "--durations", str(SLOWEST)], cwd=ROOT,
                         capture_output=True, text=True)
    minutes = (time.perf_counter() - start) / 60
    print(run.stdout[-6000:], run.stderr[-2000:], sep="\n")
    figures = {"minutes": minutes, **counts(run.stdout), "exit_status": run.returncode}
    write_result("suite-time", figures)
    print(f"RESULT minutes={minutes:.2f} passed={figures['passed']} "
          f"failed={figures['failed']} skipped={figures['skipped']}")
    return run.returncode


if __name__ == "__main__":
    sys.exit(main())
