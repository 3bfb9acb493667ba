"""Progress bars that suit where they are written.

A terminal gets tqdm's live bar; a log file (a job's redirected stderr: ``nohup``, a batch
system, ``make demo > log``) gets one update every :data:`LOG_INTERVAL_S` seconds instead of
about ten a second, which wrote some 250 kB of bar per full-size run.
"""

from __future__ import annotations

import sys
from typing import Any

#: Seconds between a bar's updates when stderr is not a terminal
LOG_INTERVAL_S = 30.0
#: tqdm's own interval, kept for a terminal
LIVE_INTERVAL_S = 0.1


def progress_bar(**kwargs: Any) -> Any:
    """A ``tqdm`` bar on stderr (``kwargs`` as tqdm's), updated at most every
    :data:`LIVE_INTERVAL_S` s on a terminal and every :data:`LOG_INTERVAL_S` s elsewhere."""
    from tqdm import tqdm

    live = bool(getattr(sys.stderr, "isatty", lambda: False)())
    return tqdm(mininterval=LIVE_INTERVAL_S if live else LOG_INTERVAL_S, **kwargs)
