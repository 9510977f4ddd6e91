"""Progress bars of long jobs (predict, eval, bench, build-db, train, gallery): tqdm on stderr,
with the rate in the job's own unit, shown only on a terminal and never with `--quiet`."""

from __future__ import annotations

import sys

from tqdm.auto import tqdm
from tqdm.contrib.logging import logging_redirect_tqdm

_quiet = False


def set_quiet(quiet: bool) -> None:
    """Silence every bar of this process (the CLI's --quiet)."""
    global _quiet
    _quiet = quiet


def progress(iterable=None, *, total: int | None = None, desc: str = "", unit: str = "it"):
    """A tqdm bar over `iterable` (or one to `update` by hand), disabled when quiet or when
    stderr is not a terminal (logs and CI stay clean)."""
    return tqdm(
        iterable,
        total=total,
        desc=desc,
        unit=unit,
        disable=_quiet or not sys.stderr.isatty(),
        dynamic_ncols=True,
        leave=False,
    )


def logging_above_bars():
    """A context manager: while it lasts, the root logger's console lines are written above the
    bars (as tqdm.write does) instead of through them; the same lines as without it."""
    return logging_redirect_tqdm(tqdm_class=tqdm)
